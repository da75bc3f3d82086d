"""The confidence's depth-scan term on estimates the registration corrected along the beam: every
recorded single-plane assessment that holds a depth scan (``confidence_evidence.depth_scan_tz_mm``)
re-decided from its stored evidence with and without the term (no registration runs).

Records made before the registration corrected its own depth (revisions that do not contain
``--since``, default eb7bdb3) are counted apart: there the scan read uncorrected estimates. A
record whose revision is not in this history (made on a branch since squashed, or without one)
is dated by the commit that added its file.

    python scripts/scan_term_rescore.py [--root docs/validation] [--since eb7bdb3]
"""

from __future__ import annotations

import argparse
import collections
import functools
import json
import subprocess
from dataclasses import fields, replace
from pathlib import Path

from registration.core.confidence import DEFAULT_RULE, Evidence

NAMES = {f.name for f in fields(Evidence)}


@functools.cache
def contains(revision: str, since: str) -> bool | None:
    """Whether ``revision`` (a record's, ``-dirty`` allowed) contains ``since`` (None: unknown here)."""
    rev = revision.removesuffix("-dirty")
    known = subprocess.run(["git", "cat-file", "-e", rev + "^{commit}"], capture_output=True).returncode == 0
    if not known:
        return None
    return subprocess.run(["git", "merge-base", "--is-ancestor", since, rev], capture_output=True).returncode == 0


@functools.cache
def added_after(path: Path, since: str) -> bool:
    """Whether the commit that added ``path`` contains ``since``."""
    out = subprocess.run(
        ["git", "log", "--diff-filter=A", "--format=%H", "--", str(path)], capture_output=True, text=True
    )
    first = out.stdout.split()[-1] if out.stdout.split() else "HEAD"
    return subprocess.run(["git", "merge-base", "--is-ancestor", since, first], capture_output=True).returncode == 0


def right(rec: dict, prefix: str) -> bool | None:
    for key in (prefix + "success_inplane", prefix + "success"):
        if key in rec:
            return bool(rec[key])
    return None


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--root", type=Path, default=Path("docs/validation"))
    p.add_argument("--since", default="eb7bdb3")
    args = p.parse_args()
    without = replace(DEFAULT_RULE, scan_weight=0.0)
    rows: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
    changed = []
    for path in sorted(args.root.rglob("*.jsonl")):
        for line in path.read_text().splitlines():
            try:
                rec = json.loads(line)
            except json.JSONDecodeError:
                continue
            for prefix in ("", "single_"):
                ev = rec.get(prefix + "confidence_evidence")
                if not isinstance(ev, dict) or ev.get("depth_scan_tz_mm") is None:
                    continue
                known = contains(str(rec.get("revision", "")), args.since)
                if known is None:
                    known = added_after(path, args.since)
                era = "corrected" if known else "before"
                e = Evidence(**{k: v for k, v in ev.items() if k in NAMES})
                a, b = DEFAULT_RULE.assess(e), without.assess(e)
                ok = right(rec, prefix)
                c = rows[era]
                c["registrations"] += 1
                c["fired"] += ev["depth_scan_tz_mm"] < DEFAULT_RULE.scan_free_mm
                c["applied with"] += a.applied
                c["applied without"] += b.applied
                c["wrong applied with"] += a.applied and ok is False
                c["wrong applied without"] += b.applied and ok is False
                if a.applied != b.applied:
                    c["changed"] += 1
                    changed.append({"era": era, "file": str(path), "case_id": rec.get("case_id"), "right": ok,
                                    "scan_tz_mm": ev["depth_scan_tz_mm"], "revision": rec.get("revision")})  # fmt: skip
    print(json.dumps({"rows": rows, "changed": changed}, indent=1))


if __name__ == "__main__":
    main()
