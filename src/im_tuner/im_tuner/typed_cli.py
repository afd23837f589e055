"""A typed command line, declared once: every option is a field of a dataclass
(:func:`option`: its text, argparse's type and choices, its default, whether it is a run
setting), from which comes the parser (:class:`OptionsParser`, whose ``parse_args`` gives
the typed object). Imports no numpy, so that an executable's ``--help`` and refusals
(the report's, the tuner's) stay quick.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace
from typing import Any

from im_drive_sim import rt
from im_drive_sim.cli import Parser, plain

#: ``Option.arg`` of the three real-time options: ``rt.add_arguments`` declares their
#: type for every executable of the loop; an executable's rows say what they do there
RT = 'rt'


@dataclass(frozen=True)
class Option:
    """One option of a typed command line.

    ``help``: Markdown, docs/tuner.md's text (``--help`` shows it plain: :func:`plain`).
    ``arg``: argparse's ``type``, ``choices``, ``metavar``, ``nargs`` or ``action``
    (:data:`RT`: the real-time options). ``default``: the value when not given (None: the
    run decides, ``shown`` says how). ``shown``: the docs' default column when not
    ``default``. ``run``: a run setting, kept in run.yaml: ``--resume`` takes it from
    there and refuses it given. ``flag``: the field's name as ``--a-b`` unless given
    (``RUN_DIR``-like positionals have no dashes); ``dest``: the field's name."""

    flag: str
    help: str
    arg: dict[str, Any] | str = field(default_factory=dict)
    default: Any = None
    shown: str = ''
    run: bool = False
    dest: str = ''


_FROM_DEFAULT = object()
#: the tuner's options by field name, and each one's value when not given, for ``like``
#: (filled by :mod:`.tuner_args`, which every executable sharing its options imports)
SHARED: dict[str, tuple[Option, Any]] = {}


def option(
    help: str,
    arg: dict[str, Any] | str | None = None,
    default: Any = None,
    shown: str = '',
    run: bool = False,
    parsed: Any = _FROM_DEFAULT,
    flag: str = '',
    like: str = '',
) -> Any:
    """A field of a typed command line declaring its option (:class:`Option`).
    ``parsed``: the value when not given, where it is not ``default`` (a run setting:
    None, so ``--resume`` can refuse it given; the real-time options: ``rt``'s).
    ``like``: another executable's field of the tuner's option of that name, the same
    flag and argparse declaration (``arg``: what differs there), with its own text and
    default."""
    arg = {} if arg is None else arg
    if like:
        base, base_parsed = SHARED[like]
        if isinstance(base.arg, dict) and isinstance(arg, dict):
            arg = {**base.arg, **arg}
        else:
            arg, parsed = RT, base_parsed
    meta = {'option': Option(flag, help, arg, default, shown, run)}
    action = arg.get('action') if isinstance(arg, dict) else None
    if action == 'append' or (isinstance(arg, dict) and arg.get('nargs') in ('*', '+')):
        return field(default_factory=list, metadata=meta)  # (a list: one per object)
    if parsed is _FROM_DEFAULT:
        parsed = False if action == 'store_true' else None if run else default
    return field(default=parsed, metadata=meta)


def declared(cls: type) -> tuple[Option, ...]:
    """The options of the typed command line ``cls``, in its fields' order."""
    return tuple(
        replace(
            f.metadata['option'],
            flag=f.metadata['option'].flag or '--' + f.name.replace('_', '-'),
            dest=f.name,
        )
        for f in fields(cls)
    )


class OptionsParser(Parser):
    """The parser of a typed command line ``cls`` (a dataclass of :func:`option` fields;
    its ``PROG``, ``DESCRIPTION`` and ``RT_WHAT``, what the real-time options schedule):
    ``parse_args`` gives a ``cls``."""

    def __init__(self, cls: type) -> None:
        super().__init__(prog=cls.PROG, description=cls.DESCRIPTION)  # type: ignore[attr-defined]
        self.options = cls
        defaults = vars(cls())
        rt_helps = {}
        for o in declared(cls):
            if o.arg == RT:
                rt_helps.update({o.flag: _help(o)} if o.help else {})
                continue
            assert isinstance(o.arg, dict)
            where = {'dest': o.dest} if o.flag.startswith('-') else {}
            self.add_argument(o.flag, help=_help(o), default=defaults[o.dest], **where, **o.arg)
        if any(o.arg == RT for o in declared(cls)):
            rt.add_arguments(self, cls.RT_WHAT, rt.DEFAULT_PRIORITY, rt_helps)  # type: ignore[attr-defined]

    def parse_args(self, args: Any = None, namespace: Any = None) -> Any:
        return self.options(**vars(super().parse_args(args, namespace)))


def _help(o: Option) -> str:
    shown = default_text(o)
    return plain(o.help) + (f' (default: {plain(shown)})' if shown else '')


def default_text(o: Option) -> str:
    """The default ``--help`` and the docs show: ``shown``, else ``default`` as text."""
    if o.shown or o.default is None or o.default is False:
        return o.shown
    return f'{o.default:g}' if isinstance(o.default, float) else str(o.default)
