"""The head-alone probe's place in the confidence (registration.core.confidence's ``spine`` term,
weighted by a rule that asks for it; the default rule does not) and when the assessment runs it
(registration.core.assess)."""

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from registration.core.assess import SPINE_PROBE_BELOW_AGREEMENT, _spine_pull
from registration.core.confidence import DEFAULT_RULE, Evidence
from registration.core.volume import Volume

#: The rule with the head-alone term weighted as the decision record measured it.
SPINE_RULE = replace(DEFAULT_RULE, spine_weight=20.0)
#: A right single-plane estimate's evidence (every other term free).
GOOD = Evidence(margin=0.005, rotation_margin=0.01, agreement=0.0, edges=0.25, depth_scan_tz_mm=1.0)


@pytest.mark.parametrize(("pull_mm", "applied"), [(None, True), (0.15, True), (0.3, True), (0.5, False), (1.4, False)])
def test_a_head_that_fits_elsewhere_withholds(pull_mm, applied) -> None:
    """Free up to 0.3 mm (right estimates on the typical clinical images moved 0.15 mm at most);
    0.45 mm costs the bias (more withholds), and the reason names the head."""
    e = Evidence(**{**GOOD.to_dict(), "spine_pull_mm": pull_mm})
    decided = SPINE_RULE.assess(e)
    assert decided.applied is applied
    if not applied:
        assert "head alone" in decided.reason and "neck" in decided.reason
    if pull_mm is not None and pull_mm >= 0.45:
        assert SPINE_RULE.terms(e)["spine"] <= -3.0


def _stand_ins(parameters: tuple[str, ...], meta: dict) -> tuple[object, object]:
    volume = Volume(np.zeros((4, 4, 4), np.float32), np.eye(4), label="v", meta=meta)
    result = SimpleNamespace(parameters=parameters, patient_motion=np.eye(4))
    return result, SimpleNamespace(volume=volume, prepared=None)


@pytest.mark.parametrize(
    ("parameters", "agreement", "meta"),
    [
        (("tx", "ty", "rx", "ry", "rz"), SPINE_PROBE_BELOW_AGREEMENT, {}),  # the capture runs agreed
        (("tx", "ty", "rx", "ry", "rz"), None, {}),  # one capture run: nothing to disagree
        (("tx", "ty", "tz", "rx", "ry", "rz"), 0.0, {}),  # two views
        (("tx", "ty", "rx", "ry", "rz"), 0.0, {"roi": {"source": "cranium"}}),  # already the head
    ],
)
def test_the_probe_runs_only_on_one_views_disputed_whole_volume_estimate(parameters, agreement, meta) -> None:
    """Skipped (None, the preparation untouched: it is a stand-in without levels) unless one view's
    capture runs disagreed on a volume that is not a region already."""
    result, preparation = _stand_ins(parameters, meta)
    view = SimpleNamespace()
    assert _spine_pull(result, [view], preparation, Evidence(agreement=agreement), SPINE_RULE) is None


def test_the_default_rule_neither_probes_nor_weights_the_head_alone() -> None:
    """Off by default (fresh draws did not justify its cost): no probe even on a disputed
    single-plane estimate of the whole volume, and a pull given costs nothing."""
    result, preparation = _stand_ins(("tx", "ty", "rx", "ry", "rz"), {})
    assert _spine_pull(result, [SimpleNamespace()], preparation, Evidence(agreement=0.0), DEFAULT_RULE) is None
    assert "spine" not in DEFAULT_RULE.terms(Evidence(**{**GOOD.to_dict(), "spine_pull_mm": 1.4}))
