"""Quality scorecard of a finished job (issue 9 part 1): the same as ``proceduralize evaluate JOB``.

    python bench/quality.py /tmp/job_small                 # prints the table, writes <job>/evaluation/metrics.*
    python bench/quality.py out/quick --no-render --out /tmp/scores

Every option of ``proceduralize evaluate`` is accepted (``--help``); see workers/evaluate.py for the protocol.
Besides the metric table it prints, per material and map, the pretrained VGG-19 Gram distance of the procedural
maps, of random-phase noise of the input and of the flat mean, in units of the input's own left-to-right
distance, then the median procedural/floor and the share of pairs where the procedural maps beat the noise.
"""
from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from service.cli import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main(["evaluate", *sys.argv[1:]]))
