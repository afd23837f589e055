"""What a closing recorder says of its per-topic counts, pure (no rclpy): the custom data
of ``metadata.yaml`` and the report it logs. A topic's counts: ``recorded``,
``published`` (as the publishers' sequence numbers tell), ``lost``, ``publishers``,
``published_before_recording``, ``unmatched_publishers``."""

from __future__ import annotations

import json
from pathlib import Path

Counts = dict[str, dict[str, int]]


def closing_custom_data(counts: Counts, unrecordable: dict[str, str], cut: str) -> dict[str, str]:
    """The bag's ``custom_data`` at close: the counts, the total lost, state ``closed``,
    the topics it could not record and why, and ``cut`` (why taking stopped early; '')."""
    custom = {
        'im_tuner.counts': json.dumps(counts, sort_keys=True),
        'im_tuner.lost_total': str(sum(c['lost'] for c in counts.values())),
        'im_tuner.state': 'closed',
    }
    if unrecordable:
        custom['im_tuner.unrecordable'] = json.dumps(unrecordable, sort_keys=True)
    if cut:
        custom['im_tuner.close'] = cut
    return custom


def counts_report(
    out: Path, message_count: int, counts: Counts, unrecordable: dict[str, str]
) -> str:
    """The lines logged at close: per topic recorded / published / lost (a loss flagged),
    then the topics not recorded."""
    lines = [f'bag {out}: {message_count} messages on {len(counts)} topics']
    for name, c in sorted(counts.items()):
        flag = '' if c['lost'] == 0 and c['unmatched_publishers'] == 0 else '   <-- LOST'
        lines.append(
            f'  {name}: recorded {c["recorded"]} / published {c["published"]}, '
            f'lost {c["lost"]}{flag}'
        )
    for name, why in unrecordable.items():
        lines.append(f'  {name}: NOT RECORDED ({why})')
    return '\n'.join(lines)
