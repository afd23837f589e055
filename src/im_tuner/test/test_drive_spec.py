"""``--drive`` against docs/real-drive.md's drive contract (im_tuner.bench.drive_spec):
which classes are drives, the one-line reasons for the others, guarded imports, and the
hardware class built once and handed to the bench."""

from __future__ import annotations

import io
import sys
import textwrap
from pathlib import Path

import pytest

from im_drive_sim.drive_file import load_config
from im_tuner.bench import drive_spec
from im_tuner.bench.drive_spec import DriveSpecError, check_drive_class, load_drive_class

MODULE = """
from abc import ABC, abstractmethod

from im_drive_sim.example_drive import Measurement

LOG = []  # (event, instance id)


class Good:
    def __init__(self, config):
        self.config = config
        self.m = Measurement()
        self.isq = 0.0
        LOG.append(('built', id(self)))

    def read(self):  # the current follows its reference at once (command delay 1)
        self.m.isq = self.isq
        return self.m

    def write(self, isq_ref, load_torque):
        self.isq = isq_ref

    def close(self):
        LOG.append(('closed', id(self)))


class StaticWrite(Good):
    @staticmethod
    def write(isq_ref, load_torque):
        pass


class ClassRead(Good):
    @classmethod
    def read(cls):
        return None


class NoWrite:
    def __init__(self, config):
        pass

    def read(self):
        return None


class ReadTakesOne(Good):
    def read(self, n):
        return None


class CloseTakesOne(Good):
    def close(self, how):
        pass


class NoConfig(Good):
    def __init__(self):
        pass


class Abstract(ABC):
    def __init__(self, config):
        pass

    @abstractmethod
    def read(self): ...

    def write(self, isq_ref, load_torque):
        pass


class Raises(Good):
    def __init__(self, config):
        raise RuntimeError('no inverter on /dev/ttyUSB0\\nsecond line')


class Exits(Good):
    def __init__(self, config):
        raise SystemExit(4)


class Latching(Good):
    command_delay = 2
    pending = 0.0

    def write(self, isq_ref, load_torque):  # latched: acts a period later
        self.isq, self.pending = self.pending, isq_ref


class DelayThree(Good):
    command_delay = 3
"""


@pytest.fixture
def hw(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    """The module ``hw_mod`` (the classes above) and two broken modules, importable."""
    (tmp_path / 'hw_mod.py').write_text(MODULE)
    (tmp_path / 'exits_mod.py').write_text('import sys\nsys.exit(3)\n')
    (tmp_path / 'raises_mod.py').write_text("raise ImportError('libinverter.so: not found')\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    for m in ('hw_mod', 'exits_mod', 'raises_mod'):
        monkeypatch.delitem(sys.modules, m, raising=False)
    monkeypatch.setattr(drive_spec, '_BUILT', [])
    import hw_mod

    hw_mod.LOG.clear()
    return hw_mod


@pytest.mark.parametrize('name', ['Good', 'StaticWrite', 'ClassRead'])
def test_hardware_classes_that_keep_the_contract(hw, name: str) -> None:
    assert check_drive_class(f'hw_mod:{name}', getattr(hw, name)) == 'hardware'
    choice = drive_spec.resolve(f'hw_mod:{name}', None, build=False)  # checked, not built
    assert (choice.spec, choice.form, choice.hardware) == (f'hw_mod:{name}', 'hardware', None)


def test_the_example_drive_forms() -> None:
    from im_drive_sim.example_drive import ExampleDrive, Hardware

    assert check_drive_class('x:Hardware', Hardware) == 'hardware'
    assert check_drive_class('x:ExampleDrive', ExampleDrive) == 'node'

    class MyDrive(ExampleDrive):
        pass

    assert check_drive_class('x:MyDrive', MyDrive) == 'node'

    class Positional(ExampleDrive):
        def __init__(self, port, **kwargs):
            super().__init__(**kwargs)

    with pytest.raises(DriveSpecError, match=r'Positional\(context=\.\.\., parameter_overr'):
        check_drive_class('x:Positional', Positional)


@pytest.mark.parametrize(
    'spec, says',
    [
        ('hw_mod:NoWrite', 'NoWrite has no write(): a hardware class has read() -> Measurement'),
        ('hw_mod:ReadTakesOne', 'ReadTakesOne.read() is not a valid call'),
        ('hw_mod:CloseTakesOne', 'CloseTakesOne.close() is not a valid call: close takes no'),
        ('hw_mod:NoConfig', 'NoConfig(config) is not a valid call'),
        ('hw_mod:Abstract', 'Abstract is abstract'),
        ('hw_mod', "expected 'sim', 'example', 'lib:PATH' or 'package.module:Class'"),
        (':Good', "expected 'sim', 'example'"),
        ('no_such_module_x:Good', 'cannot import no_such_module_x: ModuleNotFoundError'),
        ('raises_mod:Good', 'cannot import raises_mod: ImportError: libinverter.so: not found'),
        ('exits_mod:Good', 'importing exits_mod called sys.exit(3)'),
        ('hw_mod:Nothing', 'hw_mod has no class Nothing'),
        ('hw_mod:LOG', 'hw_mod has no class LOG'),
    ],
)
def test_drives_that_cannot_be_used_are_refused_saying_why(hw, spec: str, says: str) -> None:
    """What --drive does with its value: import the class (guarded), then check it."""
    with pytest.raises(DriveSpecError) as exc:
        check_drive_class(spec, load_drive_class(spec))
    msg = str(exc.value)
    assert msg.startswith(f'--drive {spec!r}: ') and says in msg and '\n' not in msg


def test_ros_nodes_that_are_not_drives_and_other_objects() -> None:
    from rclpy.node import Node

    with pytest.raises(DriveSpecError, match='Node is a ROS node but not a drive node'):
        check_drive_class('rclpy.node:Node', Node)
    with pytest.raises(DriveSpecError, match=r'BytesIO\.write\(isq_ref, load_torque\) is not'):
        check_drive_class('io:BytesIO', io.BytesIO)
    with pytest.raises(DriveSpecError, match='has no read'):
        check_drive_class('builtins:dict', dict)


def test_the_hardware_is_built_once_and_handed_to_the_bench(hw) -> None:
    choice = drive_spec.resolve('hw_mod:Good', None)
    assert choice.form == 'hardware' and [e for e, _ in hw.LOG] == ['built']
    config = load_config(None)
    assert choice.config == config
    # the example drive loads the same file: it gets the instance built by the check
    assert choice.factory(config) is choice.hardware and choice.taken
    drive_spec.close_untaken()  # taken: the bench closes it, not the tuner
    assert [e for e, _ in hw.LOG] == ['built']


def test_an_untaken_instance_is_closed_and_another_file_builds_anew(hw, tmp_path) -> None:
    choice = drive_spec.resolve('hw_mod:Good', None)
    first = choice.hardware
    other = tmp_path / 'other.yaml'
    other.write_text('base: paper_750w\nmachine:\n  isq_max: 5.0\n')
    second = choice.factory(load_config(other))  # (-p config_file: another drive file)
    assert second is not first and second.config.machine.isq_max == 5.0
    assert [('built', id(first)), ('closed', id(first)), ('built', id(second))] == hw.LOG
    hw.LOG.clear()
    third = drive_spec.resolve('hw_mod:Good', None).hardware
    drive_spec.close_untaken()  # a refused run: the tuner closes what no bench took
    assert [('built', id(third)), ('closed', id(third))] == hw.LOG


def test_a_constructor_that_raises_or_exits_is_one_line_naming_it(hw) -> None:
    with pytest.raises(DriveSpecError) as exc:
        drive_spec.resolve('hw_mod:Raises', None)
    assert str(exc.value) == (
        "--drive 'hw_mod:Raises': Raises(config) raised RuntimeError: no inverter on /dev/ttyUSB0"
    )
    with pytest.raises(DriveSpecError, match=r'Exits\(config\) called sys\.exit\(4\)'):
        drive_spec.resolve('hw_mod:Exits', None)
    assert drive_spec.resolve('hw_mod:Raises', None, build=False).hardware is None
    assert drive_spec.resolve('sim', None).cls is None


def test_the_drive_file_is_checked_with_the_spec(hw, tmp_path) -> None:
    bad = tmp_path / 'bad.yaml'
    bad.write_text(textwrap.dedent('# only a comment\n'))
    with pytest.raises(DriveSpecError, match=r'bad\.yaml: no settings'):
        drive_spec.resolve('hw_mod:Good', bad)
    assert hw.LOG == []


def test_a_declared_command_delay_is_checked_when_the_hardware_is_built(hw) -> None:
    """``command_delay`` (docs/real-drive.md): 1 or 2; anything else is refused in one line
    and the instance built is closed."""
    assert drive_spec.resolve('hw_mod:Latching', None).hardware.command_delay == 2
    drive_spec.close_untaken()
    hw.LOG.clear()
    with pytest.raises(DriveSpecError) as exc:
        drive_spec.resolve('hw_mod:DelayThree', None)
    msg = str(exc.value)
    assert 'DelayThree.command_delay must be 1 or 2 (periods), got 3' in msg and '\n' not in msg
    assert [e for e, _ in hw.LOG] == ['built', 'closed']
