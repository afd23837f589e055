"""The tuner: ``ros2 run im_tuner tuner --algo {spsa,necga,cga,pecga,rcga}``.

Tunes the five gains of the cascaded position controller (paper eq. 8) online: for each
evaluation it sets the gains on the controller through its parameter services
(atomically), starts the paper's experiment, waits for the loss, and tells the optimiser
(:mod:`im_tuner.tuning`, :mod:`im_tuner.link`, :mod:`im_tuner.optim`).

The benches, the recording and the run directory: docs/tuner.md; the pieces this module
wires (parse, spec, open, run, close): docs/architecture.md. Bench processes started here
end with the tuner, however it ends.

Exit codes: 0 done, 1 the bench failed (best gains applied, bag closed), 2 bad input,
130 interrupted (SIGINT/SIGTERM; resumable).
"""

from __future__ import annotations

import sys
import time

# Only what parsing and checking need: rclpy, the benches, numba kernels, pycma... are
# imported once every check passed (tuner_cli), so a refusal is one line at once.
from im_drive_sim.cli import EXIT_FAILED, EXIT_INTERRUPTED, EXIT_USAGE, UsageError, check_ros_args

from . import optim
from .bench.spec import tuner_bench_spec
from .benches import SIM_BENCHES
from .tuner_args import TunerOptions, parse_options, ros_arguments
from .tuner_cli import RunFinished, check_session, prepare_run


def main(args: list[str] | None = None) -> int:
    argv = list(sys.argv if args is None else args)
    try:
        cli = parse_options(check_ros_args(argv)[1:])
        if 'help' in cli.opt:  # the algorithm's options, as --help the tuner's
            print(optim.describe_options(cli.algo or optim.DEFAULT_ALGO))
            return 0
        check_session(cli)
        return _main(cli, argv)
    except UsageError as exc:
        print(f'error: tuner: {exc}', file=sys.stderr)
        return EXIT_USAGE
    except RunFinished as exc:
        print(f'tuner: {exc}', flush=True)
        return 0
    finally:
        # a hardware class built by the checks and never taken by a bench (a refusal or a
        # failure on the way): closed, whatever the way out
        spec = sys.modules.get('im_tuner.bench.drive_spec')
        if spec is not None:
            spec.close_untaken()


def _main(cli: TunerOptions, argv: list[str]) -> int:
    t_wall0 = time.monotonic()
    cfg = prepare_run(cli, argv)  # every check before anything is created
    spec = tuner_bench_spec(
        cli,
        cfg.run,
        resumed=cli.resume is not None,
        records=cfg.tuning.records if cfg.tuning is not None else [],
        drive_choice=cfg.drive,
    )
    from rclpy.context import Context
    from rclpy.node import Node

    from im_drive_sim.runtime import RosSession

    from .bench.forms import Bench, Executor
    from .bench.open import open_bench
    from .link import ControllerLink, Heartbeat
    from .names import controller_topics
    from .result_msg import ResultPublisher
    from .tuner_session import TunerSession
    from .tuning import BenchFailure, ResumeError, StopRequested

    session = TunerSession(cli, argv, cfg)
    ctx = Context()
    ros = RosSession(ros_arguments(argv, cfg.run if cli.resume is not None else None), context=ctx)

    def should_stop() -> bool:
        return ros.stopped

    bench: Bench | None = None
    node = exe = None
    heartbeat = None
    discard_bag = refused = False
    try:
        node = Node('tuner', context=ctx, start_parameter_services=False)
        exe = Executor(ctx)
        exe.executor.add_node(node)
        # before the bench: its recorder finds the topic when it starts
        results = ResultPublisher(node, controller_topics(cli.controller)['result'])
        bench = open_bench(
            spec, session, context=ctx, node=node, exe=exe, command=argv, should_stop=should_stop
        )
        session.accepted()
        tuning = session.tuning
        tuning.on_record = results
        if bench.plan.mode == 'external' and cfg.run.drive_config is None and tuning.first_step:
            # --bench auto found someone's controller: its drive is not the packaged one
            tuning.first_step = None
            session.progress.note(
                'note: the controller on the graph drives a drive this tuner does not know '
                "(no --drive-config): safe's first step is not identified from it"
            )
        link = ControllerLink(
            node,
            bench.spin_until,
            controller=cli.controller,
            eval_timeout=cli.eval_timeout,
            fault_policy=bench.plan.fault_policy,
            owns_controller=bench.plan.mode in SIM_BENCHES,
            should_stop=should_stop,
            supervise=bench.supervise,
            call_timeout=min(10.0, cli.eval_timeout),
        )
        if bench.plan.mode == 'external':
            # a controller of its own (a drive host's): its tuner watchdog hears us
            heartbeat = Heartbeat(node, link.names['heartbeat'])
        if not link.wait_ready(30.0):
            raise BenchFailure(
                f'the controller {cli.controller} did not become reachable '
                'within 30 s (services and loss topic)'
            )
        loss_topic = link.names['loss']
        if not bench.recording_ready(
            30.0, lambda: {loss_topic: link.loss_messages, results.topic: results.published}
        ):
            raise BenchFailure(
                'the recorder child did not subscribe to and match every recorded topic within 30 s'
            )
        bench.session_start()
        session.start(link)
        outcome = session.tuning.run(link, should_stop)
        code = session.finish(outcome, bench, link, t_wall0)
    except (BenchFailure, ResumeError) as exc:
        session.progress.close()
        print(f'error: tuner: {exc}', file=sys.stderr)
        code = EXIT_USAGE if isinstance(exc, ResumeError) else EXIT_FAILED
        # a replay that does not match refuses the resume: its bag holds only the replay
        discard_bag = isinstance(exc, ResumeError)
    except StopRequested:
        session.progress.close()
        print('tuner: interrupted before the search started', file=sys.stderr)
        code = EXIT_INTERRUPTED
    except UsageError:
        refused = True
        raise
    finally:
        if heartbeat is not None:
            heartbeat.stop()
        if bench is not None:
            bench.close()
        if discard_bag:
            session.discard_bag()
        if node is not None:
            node.destroy_node()
        if exe is not None:
            exe.executor.shutdown()
        ros.close()
        if refused:  # refused by the bench after the run directory was made: undo it
            session.undo()
    return code


if __name__ == '__main__':
    from im_drive_sim.cli import executable

    executable('tuner', main)
