"""The default rule against the data it was calibrated on: the clinical study's seeds 0, 1 and 2
(docs/validation/clinical-200/calibration_evidence.json: the evidence of 340 single-plane
registrations beside their residuals against the truth; seeds 0 and 1 for revision 1 of the
single-plane terms, seed 2 added for revision 2's ``depth_pull``). No registration runs here: the
rule is a function of the recorded evidence, and right = in-plane < 1 mm and rotation < 3 degrees."""

import json
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
    # measured: 291 applied, 4 wrong (in-plane near misses 1.00-1.26 mm), 309 right: 98.6 % /
    # 92.9 %; revision 1 applied 293 with 6 wrong (98.0 %). The 99 % target is not reached on
    # the data the rule was fitted to: the in-plane error grows with the out-of-plane offset the
    # single view cannot measure (about 0.05 mm per mm).
    assert sum(applied) == 291
    assert sum(a and not r for a, r in zip(applied, right, strict=True)) == 4
    assert precision == pytest.approx(287 / 291)
    assert recall == pytest.approx(287 / 309)


def test_seeds_0_and_1_keep_their_decisions_under_revision_2(records):
    # depth_pull does not fire on seeds 0 and 1 (no probe tz below -7 mm): 121 applied, 1 wrong
    early = [r for r in records if r["study_seed"] in (0, 1)]
    applied, right = _counts(early)
    assert sum(applied) == 121
    assert sum(a and not r for a, r in zip(applied, right, strict=True)) == 1


def test_depth_pull_withholds_the_estimates_the_measure_pulls_away_from_the_source(records):
    pulled = [r for r in records if r["evidence"]["depth_tz_mm"] < DEFAULT_RULE.pull_free_mm - 3.0]
    assert pulled  # seed 2's near misses at -10.6 to -15.4 mm
    for r in pulled:
        assert DEFAULT_RULE.terms(Evidence(**r["evidence"]))["depth_pull"] <= -3.0
