"""Re-decide stored two-view assessments with and without the confidence term ``planes_apart``.

Run: ``python scripts/planes_apart_rescore.py [RESULTS.jsonl ...]`` (default: every ``*.jsonl``
under ``docs/validation``).

A record counts when it holds its ``confidence_evidence`` and either that evidence's
``planes_apart`` or the registration's stages, among them the planes' own captures (then
``planes_apart`` is whether a stage that runs only when the planes disagree ran). The rule's
decision without the term (``apart_weight=0``) must equal the recorded one for records made
before the term; both decisions are counted against each record's ``success``, and every record
whose decision changes is listed.
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import glob
import json

from registration.core.confidence import ConfidenceRule, Evidence
from registration.core.register.plan import PLANES_DISAGREE

FIELDS = {f.name for f in dataclasses.fields(Evidence)}


def planes_apart(record: dict) -> bool | None:
    """The record's ``planes_apart``: from its evidence, else from its stages (None: not a
    two-view registration with the planes' own captures)."""
    evidence = record["confidence_evidence"]
    if evidence.get("planes_apart") is not None:
        return bool(evidence["planes_apart"])
    stages = record.get("stages")
    if not isinstance(stages, list):
        return None
    names = [s.get("stage", "") for s in stages if isinstance(s, dict)]
    if not any("each plane's own capture" in n for n in names):
        return None
    return any(n.endswith(f"({PLANES_DISAGREE[0]})") for n in names)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("paths", nargs="*", help="results.jsonl files")
    paths = parser.parse_args().paths or sorted(glob.glob("docs/validation/**/*.jsonl", recursive=True))
    with_term, without = ConfidenceRule(), ConfidenceRule(apart_weight=0.0)
    counts: collections.Counter = collections.Counter()
    changed = []
    for path in paths:
        for line in open(path, encoding="utf-8"):
            try:
                record = json.loads(line)
            except json.JSONDecodeError:
                continue
            if not isinstance(record.get("confidence_evidence"), dict):
                continue
            apart = planes_apart(record)
            if apart is None:
                continue
            known = {k: v for k, v in record["confidence_evidence"].items() if k in FIELDS}
            evidence = Evidence(**(known | {"planes_apart": float(apart)}))
            old, new = without.assess(evidence), with_term.assess(evidence)
            right = bool(record.get("success"))
            counts["two-view registrations"] += 1
            counts["planes disagreed"] += apart
            counts["recorded decision = without the term"] += old.applied == record.get("applied")
            counts["applied without the term"] += old.applied
            counts["applied and wrong without the term"] += old.applied and not right
            counts["applied with the term"] += new.applied
            counts["applied and wrong with the term"] += new.applied and not right
            if old.applied != new.applied:
                case = record.get("case_id", record.get("case"))
                confidence = [round(old.confidence, 3), round(new.confidence, 3)]
                changed.append({"file": path, "case": case, "right": right, "margin": known.get("margin"),
                                "confidence": confidence})  # fmt: skip
    print(json.dumps({"counts": dict(counts), "changed": changed}, indent=1))


if __name__ == "__main__":
    main()
