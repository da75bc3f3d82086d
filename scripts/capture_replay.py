"""Chosen moments of the full capture study (the same draws as ``validate capture --seed S``),
registered under one of ``plane_capture_study.py``'s arm sets; one JSON line per moment and arm.

    PYTHONPATH=. python scripts/capture_replay.py 1 translation /50mm-0deg/r1/,/50mm-0deg/r4/ beam-line

Arguments: the study seed, the sweeps (comma-separated), parts of the case ids to register
(comma-separated), the arm set (default ``beam-line``).
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from plane_capture_study import ARM_SETS, _line  # noqa: E402

from registration.studies.capture import CaptureConfig, capture_tasks  # noqa: E402
from registration.studies.execution import execute  # noqa: E402


def main() -> None:
    seed, sweeps, wanted = int(sys.argv[1]), tuple(sys.argv[2].split(",")), sys.argv[3].split(",")
    arms = ARM_SETS[sys.argv[4] if len(sys.argv) > 4 else "beam-line"]
    config = dataclasses.replace(CaptureConfig(seed=seed), sweeps=sweeps)
    for arm, options in arms.items():
        for task in capture_tasks(config, options):
            if any(w in task.case_id for w in wanted):
                print(_line(arm, task.case_id, execute(task)), flush=True)


if __name__ == "__main__":
    main()
