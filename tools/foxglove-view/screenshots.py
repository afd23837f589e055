"""docs/foxglove/*.png: each shipped layout in Foxglove Studio's own app, from a real run.

    python tools/foxglove-view/screenshots.py OUT_DIR     (make foxglove-screenshots)

Runs the viewer test's live run (test/test_foxglove_viewer.py: ``start_live_run``, the same
command and server) with the viewer connected, saving ``fig5_trajectory_live.png`` while the
run goes on, then opens the run's bag as a file and saves ``<layout>.png`` for each layout
(1280x800 PNG; a layout with tabs: its first tab). Bad input: one line, exit 2.
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / 'test'))

import test_foxglove_viewer as tv  # noqa: E402 (the test's run and viewer, one definition)

#: the layout shown in the live screenshot
LIVE = 'fig5_trajectory'


def main() -> None:
    if len(sys.argv) != 2:
        sys.exit('usage: screenshots.py OUT_DIR')
    missing = tv._missing()
    if missing:
        print(f'screenshots.py: {missing}', file=sys.stderr)
        sys.exit(2)
    out = Path(sys.argv[1]).resolve()
    out.mkdir(parents=True, exist_ok=True)
    layouts_dir = Path(tv.get_package_share_directory('im_tuner')) / 'foxglove'
    with tempfile.TemporaryDirectory(prefix='im_tuner_screenshots_') as tmp:
        run_dir = Path(tmp) / 'run'
        shots = ('--screenshots', str(out), '--shots', LIVE, '--suffix', '_live')
        tv.watch_live_run(layouts_dir, run_dir, *shots)
        bag = sorted((run_dir / 'bag_0').glob('*.mcap'))[0]
        shots = ('--screenshots', str(out))
        tv.finish(
            tv.view('--layouts', str(layouts_dir), '--bag', str(bag), *shots),
            tv.BAG_DEADLINE_S,
            'the bag viewer',
        )
    for f in sorted(out.glob('*.png')):
        print(f)


if __name__ == '__main__':
    main()
