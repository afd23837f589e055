"""``ros2 run im_tuner sim_bench``: checks its command line before the node is imported."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from im_drive_sim.cli import UsageError, check_then_run, drive_file, executable, int_in

from ..tuner_args import OptionsParser, option
from .spec import recording_options

CONFIG_HELP = 'drive parameter file (YAML) or packaged drive name (im3700w-j3, ...): '


@dataclass
class SimulatorOptions:
    """The options of a bench that is not a run (sim_bench, drive_host): the simulated
    drive's and the bag's (:mod:`..tuner_args`)."""

    drive_config: Path | None = option(
        CONFIG_HELP + 'the simulated motor', {'type': drive_file}, like='drive_config'
    )
    model: str | None = option('drive model fidelity', like='model')
    seed: int | None = option(
        'disturbance seed (>= 0)', {'type': int_in(0, 2**31 - 1)}, like='seed'
    )
    no_record: bool = option(
        'do not record (default: all traffic to a bag, see --out); refused with --out or '
        '--compression, which would be ignored',
        like='no_record',
    )
    out: Path | None = option(
        'bag directory to create (default: bags/<executable>_<UTC time>)', like='out'
    )
    compression: str | None = option(
        'MCAP chunk compression of the bag (zstd: smaller files)', shown='lz4', like='compression'
    )

    def check_bag(self) -> None:
        """A bag option with ``--no-record`` is refused (it would be ignored), ``--out``
        must be new and creatable; the compression defaults to lz4."""
        self.compression = recording_options(
            self.no_record, out=self.out, compression=self.compression
        )
        if self.out is not None and self.out.exists():
            raise UsageError(f'--out {self.out}: already exists; choose a new directory')
        if self.out is not None:
            from ..rundir import check_creatable

            check_creatable(self.out, UsageError)


@dataclass
class SimBenchOptions(SimulatorOptions):
    """sim_bench's command line, typed."""

    PROG = 'ros2 run im_tuner sim_bench'
    DESCRIPTION = (
        'The simulated bench: drive_sim + controller, lock-step. Start experiments with '
        '/controller/start_experiment (std_srvs/Trigger); results on /controller/loss.'
    )

    processes: bool = option(
        'run drive_sim and controller as two processes (default: one)',
        {'action': 'store_true'},
    )


def parser() -> OptionsParser:
    return OptionsParser(SimBenchOptions)


def main() -> int:
    """The executable (``ros2 run``: :mod:`im_drive_sim.launch`)."""
    return check_then_run('sim_bench', parser, 'im_tuner.bench.sim_bench:main')


if __name__ == '__main__':
    executable('sim_bench', main)
