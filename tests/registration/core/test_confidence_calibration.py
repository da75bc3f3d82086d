"""The default rule against the data it was calibrated on: the clinical study's seeds 0 and 1
(docs/validation/clinical-200/calibration_evidence.json: the evidence of 140 single-plane
registrations beside their residuals against the truth). No registration runs here: the rule is
a function of the recorded evidence, and right = in-plane < 1 mm and rotation < 3 degrees."""

import json
from pathlib import Path

import pytest

from registration.core.confidence import DEFAULT_RULE, Evidence, precision_recall

EVIDENCE = Path(__file__).parents[3] / "docs" / "validation" / "clinical-200" / "calibration_evidence.json"


@pytest.fixture(scope="module")
def records():
    data = json.loads(EVIDENCE.read_text())
    assert len(data) == 140 and {r["study_seed"] for r in data} == {0, 1}
    return data


def test_every_calibration_rotation_failure_is_withheld_by_the_rotation_term_alone(records):
    failures = [r for r in records if r["rot"] >= 3.0]
    assert len(failures) == 7  # 3-13 degrees off, in-plane mostly fine
    for r in failures:
        e = Evidence(**r["evidence"])
        assert not DEFAULT_RULE.assess(e).applied, r["case_id"]
        # bias + the rotation term alone already withholds it (whatever the other terms say)
        assert DEFAULT_RULE.bias + DEFAULT_RULE.terms(e)["rotation_margin"] <= 0.0, r["case_id"]


def test_precision_and_recall_on_the_calibration_seeds(records):
    applied = [DEFAULT_RULE.assess(Evidence(**r["evidence"])).applied for r in records]
    right = [r["inplane"] < 1.0 and r["rot"] < 3.0 for r in records]
    precision, recall = precision_recall(applied, right)
    # measured: 121 applied, 1 wrong (a 1.26 mm lateral near miss), 129 right: 99.2 % / 93.0 %;
    # the targets of issue 13 (99 % / 90 %) on the data the rule was fitted to
    assert sum(applied) == 121
    assert precision == pytest.approx(120 / 121)
    assert recall == pytest.approx(120 / 129)
