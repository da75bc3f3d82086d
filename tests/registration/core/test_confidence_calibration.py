"""The default rule against the data it was calibrated on: the clinical study's seeds 0, 1 and 2
(docs/validation/clinical-200/calibration_evidence.json: the evidence of 340 single-plane
registrations beside their residuals against the truth; seeds 0 and 1 for revision 1 of the
single-plane terms, seed 2 added for revision 2's ``depth_pull``, which seed 4 then voted out).
No registration runs here: the rule is a function of the recorded evidence, and right =
in-plane < 1 mm and rotation < 3 degrees."""

import json
from dataclasses import replace
from pathlib import Path

import pytest

from registration.core.confidence import DEFAULT_RULE, Evidence, precision_recall

EVIDENCE = Path(__file__).parents[3] / "docs" / "validation" / "clinical-200" / "calibration_evidence.json"


@pytest.fixture(scope="module")
def records():
    data = json.loads(EVIDENCE.read_text())
    assert len(data) == 340 and {r["study_seed"] for r in data} == {0, 1, 2}
    return data


def _counts(records):
    applied = [DEFAULT_RULE.assess(Evidence(**r["evidence"])).applied for r in records]
    right = [r["inplane"] < 1.0 and r["rot"] < 3.0 for r in records]
    return applied, right


def test_every_rotation_failure_of_seeds_0_and_1_is_withheld_by_the_rotation_term_alone(records):
    failures = [r for r in records if r["rot"] >= 3.0 and r["study_seed"] in (0, 1)]
    assert len(failures) == 7  # 3-13 degrees off, in-plane mostly fine
    for r in failures:
        e = Evidence(**r["evidence"])
        assert not DEFAULT_RULE.assess(e).applied, r["case_id"]
        # bias + the rotation term alone already withholds it (whatever the other terms say)
        assert DEFAULT_RULE.bias + DEFAULT_RULE.terms(e)["rotation_margin"] <= 0.0, r["case_id"]


def test_precision_and_recall_on_the_calibration_seeds(records):
    applied, right = _counts(records)
    precision, recall = precision_recall(applied, right)
    # measured (the default rule, revision 1's terms): 296 applied, 7 wrong (in-plane near misses
    # 1.00-1.26 mm), 309 right: 97.6 % / 93.5 %. The 99 % target is not reached on the data the
    # rule was fitted to: the in-plane error grows with the out-of-plane offset the single view
    # cannot measure (about 0.05 mm per mm).
    assert sum(applied) == 296
    assert sum(a and not r for a, r in zip(applied, right, strict=True)) == 7
    assert precision == pytest.approx(289 / 296)
    assert recall == pytest.approx(289 / 309)


def test_seeds_0_and_1_decisions(records):
    # 121 applied, 1 wrong (a 1.26 mm lateral near miss), 129 right: 99.2 % / 93.0 %
    early = [r for r in records if r["study_seed"] in (0, 1)]
    applied, right = _counts(early)
    assert sum(applied) == 121
    assert sum(a and not r for a, r in zip(applied, right, strict=True)) == 1


def test_revision_2s_depth_pull_when_weighted(records):
    # revision 2 (pull_weight 1, knee -7 mm; not the default since seed 4): on seeds 0-2 it
    # withholds 3 of seed 2's near misses at -10.6 to -15.4 mm: 291 applied, 4 wrong
    rule = replace(DEFAULT_RULE, pull_weight=1.0)
    assert "depth_pull" not in DEFAULT_RULE.terms(Evidence(**records[0]["evidence"]))
    pulled = [r for r in records if r["evidence"]["depth_tz_mm"] < rule.pull_free_mm - 3.0]
    assert pulled
    for r in pulled:
        assert rule.terms(Evidence(**r["evidence"]))["depth_pull"] <= -3.0
    applied = [rule.assess(Evidence(**r["evidence"])).applied for r in records]
    right = [r["inplane"] < 1.0 and r["rot"] < 3.0 for r in records]
    assert sum(applied) == 291
    assert sum(a and not g for a, g in zip(applied, right, strict=True)) == 4
