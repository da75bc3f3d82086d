"""Re-score a study's results.jsonl with the current confidence rule, from the evidence each
record holds (no registration runs): ``confidence``, ``applied`` and ``withheld_reason`` are
recomputed by :data:`registration.core.confidence.DEFAULT_RULE`; the registrations, their
residuals and the evidence are left as they are. The record gets ``rescored_by`` (this
source's revision) so a reader can tell.

Used for docs/validation/clinical-s4: its registrations ran on a9477f3 (then 67ebb01 on the
branch), whose rule had a term dropped before any seed-4 result was read (1e092d6); every
field the rule reads was recorded.

    python scripts/rescore_confidence.py RESULTS.jsonl [--check]
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
from pathlib import Path

from registration.core.confidence import DEFAULT_RULE, Evidence
from registration.studies.report_kit import source_revision


def rescore(path: Path, *, write: bool = True) -> tuple[int, int]:
    lines = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    changed = 0
    revision = source_revision()
    for rec in lines:
        a = DEFAULT_RULE.assess(Evidence(**rec["confidence_evidence"]))
        if a.applied != rec["applied"]:
            changed += 1
        rec.update(confidence=a.confidence, applied=a.applied, withheld_reason=a.reason, rescored_by=revision)
    if write:
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".rescore-")
        with os.fdopen(fd, "w") as f:
            f.writelines(json.dumps(rec, default=float) + "\n" for rec in lines)
        os.replace(tmp, path)
    return len(lines), changed


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("results", type=Path)
    p.add_argument("--check", action="store_true", help="count the decisions that change; write nothing")
    args = p.parse_args()
    n, changed = rescore(args.results, write=not args.check)
    print(f"{args.results}: {n} records, {changed} decisions changed{'' if args.check else ' (rewritten)'}")


if __name__ == "__main__":
    main()
