"""The standstill-ripple limit, in one place: its default, its value, the bound it sets
from a run's records, what the search is told above it, the gains it lets the run
re-measure and apply, and what the summary says of it.

A tuned position controller can rest in a limit cycle of the encoder's last count, which
the paper's loss barely sees.  A run with a limit R keeps the gains it applies within R
times the start's rms of isq* in each standstill window (after the move, after the load;
the records' ``ripple``).  Why rms and these numbers: docs/optimisers.md, "The standstill
ripple".  Pure: the records only.
"""

from __future__ import annotations

import math
from typing import Any

from .records import Evaluation, Record

#: The limit of a run that names none, for the algorithms declared ``ripple_limited``
#: (optim.ALGORITHMS: safe); off for the others, whose final controller is the paper's.
DEFAULT_RIPPLE_LIMIT = 1.5


def default_ripple_limit(algo: str) -> float | None:
    """The ripple limit of a run of ``algo`` when none is given (None: off)."""
    from .. import optim  # (numpy: not for a reader of the run's files, the report)

    return DEFAULT_RIPPLE_LIMIT if algo in optim.RIPPLE_LIMITED else None


def parse_ripple_limit(text: str) -> float | None:
    """``--ripple-limit``'s value: a ratio > 1 (finite) or 'off' (None). ValueError
    (one line) for anything else.  Below 1 even the start would break it."""
    if text.strip().lower() == 'off':
        return None
    try:
        v = float(text)
    except ValueError:
        v = math.nan
    if not (v >= 1.0 and v < float('inf')):
        raise ValueError(f"--ripple-limit: a ratio >= 1 or 'off', got {text!r}")
    return v


def ripple_of_gains(
    records: list[Record], gains: dict[str, float] | None
) -> dict[str, float | None] | None:
    """The standstill ripple of ``gains``: each key of the records' ``ripple`` (A) averaged
    over the completed experiments of those gains (None: no experiment measured it)."""
    rs = [
        r.ripple
        for r in records
        if gains is not None and r.gains == gains and r.status == 'ok' and r.ripple
    ]
    if not rs:
        return None
    out: dict[str, float | None] = {}
    for k in rs[0]:
        v = [float(x) for r in rs if (x := r.get(k)) is not None]
        out[k] = sum(v) / len(v) if v else None
    return out


#: The windows the ripple limit checks: the rms of isq* after the move and after the load.
LIMIT_KEYS = ('rms_after_move', 'rms_after_load')


def ripple_bound(records: list[Record], limit: float | None) -> dict[str, float] | None:
    """The ripple limit in A: ``limit`` x the start's rms (:func:`ripple_of_gains` of the
    reference's gains) in each window of ``LIMIT_KEYS``, i.e. rms_choice,w <= limit x
    rms_start,w; a window where the start rests at rms 0 is not bounded (nothing to be
    louder than).  None: no limit, or the start's ripple not measured (no reference)."""
    if limit is None:
        return None
    ref = next((r for r in records if r.kind == 'reference'), None)
    start = ripple_of_gains(records, None if ref is None else ref.gains)
    if start is None:
        return None
    bound = {k: limit * float(v) for k in LIMIT_KEYS if (v := start.get(k))}
    return bound or None


def within_limit(
    records: list[Record], gains: dict[str, float], bound: dict[str, float] | None
) -> bool:
    """Whether the mean standstill rms of ``gains`` is within ``bound`` in every window it
    bounds (True without a bound; False where a bounded window was not measured)."""
    if bound is None:
        return True
    rip = ripple_of_gains(records, gains)
    if rip is None:
        return False
    return all((v := rip.get(k)) is not None and v <= b for k, b in bound.items())


def top_evals(records: list[Record], k: int, bound: dict[str, float] | None = None) -> list[int]:
    """Indices of the ``k`` best distinct (by gains) completed evaluations by measured
    loss (ties: the earlier), only those :func:`within_limit` of ``bound``: what the run
    re-measures at its end."""
    seen, out = set(), []
    evals = sorted(
        (r for r in records if isinstance(r, Evaluation) and r.status == 'ok'),
        key=lambda r: (r.loss, r.eval),
    )
    for r in evals:
        key = tuple(sorted(r.gains.items()))
        if key in seen:
            continue
        seen.add(key)
        if not within_limit(records, r.gains, bound):
            continue
        out.append(r.eval)
        if len(out) == k:
            break
    return out


#: Above the ripple limit the loss told to the optimiser is multiplied by
#: 1 + RIPPLE_PENALTY (r - 1), r = the experiment's rms over the limit's bound
#: (:func:`told_loss`; docs/optimisers.md, "The standstill ripple", says why 1).
RIPPLE_PENALTY = 1.0

#: One experiment's standstill rms scatters about its gains' mean (on ``bench``: the
#: random load and the current sensor's noise), so :func:`told_loss` penalises it only
#: above RIPPLE_TOLERANCE x the limit's bound: a point that is quiet on average is not
#: told it is loud for one loud experiment (docs/optimisers.md, "The standstill ripple").
#: The final choice keeps the strict bound on the mean (:func:`within_limit`).
RIPPLE_TOLERANCE = 1.4


def _over(rip: dict[str, Any] | None, bound: dict[str, float]) -> float | None:
    """The largest of one experiment's standstill rms over ``bound`` in the windows it
    bounds (None: a bounded window not measured)."""
    if not rip:
        return None
    r = [float(v) / b for k, b in bound.items() if (v := rip.get(k)) is not None]
    return max(r) if len(r) == len(bound) else None


def told_loss(records: list[Record], rec: Evaluation, ripple_limit: float | None) -> float:
    """The loss the optimiser is told for evaluation ``rec`` (``records``: those before
    it): the measured L, but with its rms r times the bound above RIPPLE_TOLERANCE
    ``max(L (1 + RIPPLE_PENALTY (r - 1)), L_quiet)``, L_quiet the smallest loss measured
    within the limit so far: a loud point is never better than a quiet one found, and the
    louder costs more.  An aborted experiment (already penalised), no limit or no
    measured start: L."""
    if ripple_limit is None or rec.aborted or rec.loss is None:
        return rec.loss
    bound = ripple_bound(records, ripple_limit)
    if bound is None:
        return rec.loss
    quiet = [
        x.loss
        for x in records
        if isinstance(x, Evaluation)
        and x.status == 'ok'
        and (q := _over(x.ripple, bound)) is not None
        and q <= 1.0
    ]
    return told(rec.loss, _over(rec.ripple, bound), min(quiet, default=-math.inf))


def told(
    loss: float, over: float | None, quiet: float, tolerance: float = RIPPLE_TOLERANCE
) -> float:
    """:func:`told_loss`'s rule for one experiment (also the first step's offline search,
    with no tolerance): ``over`` its largest rms over the bound (None: the loss),
    ``quiet`` the smallest loss within the limit so far (-inf: none)."""
    if over is None or over <= tolerance:
        return loss
    return max(loss * (1.0 + RIPPLE_PENALTY * (over - 1.0)), quiet)


def ripple_summary(
    records: list[Record],
    final: dict[str, Any] | None,
    ripple_limit: float | None = None,
    remeasure: int = 0,
) -> dict[str, Any] | None:
    """The standstill ripple of the start and of the applied gains (:func:`ripple_of_gains`)
    and the limit: ``limit``, ``bound``, ``applied_within``, ``excluded`` (the best
    ``max(remeasure, 1)`` distinct evaluations it kept out), ``changed`` (any) and
    ``fallback`` (none within it: the start applied); docs/tuner.md lists the keys."""
    ref = next((r for r in records if r.kind == 'reference'), None)
    start = ripple_of_gains(records, None if ref is None else ref.gains)
    applied = ripple_of_gains(records, None if final is None else final['gains'])
    if start is None and applied is None and ripple_limit is None:
        return None
    out: dict[str, Any] = {'start': start, 'applied': applied}
    bound = ripple_bound(records, ripple_limit)
    k = max(int(remeasure), 1)
    excluded = (
        []
        if bound is None
        else [i for i in top_evals(records, k) if i not in top_evals(records, k, bound)]
    )
    out['limit'] = ripple_limit
    out['bound'] = bound
    out['applied_within'] = (
        None if bound is None or final is None else within_limit(records, final['gains'], bound)
    )
    out['changed'] = bool(excluded)
    out['excluded'] = excluded
    out['fallback'] = bool(
        bound is not None
        and final is not None
        and final['eval'] < 0
        and not top_evals(records, 1, bound)
    )
    return out
