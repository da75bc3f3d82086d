"""The global start: the search box walks when the estimate ends on its bounds."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pytest

from registration.core.assess import veto
from registration.core.geometry import CArm
from registration.core.register import RegistrationOptions, StartOptions, register
from registration.core.register import walk as walk_module


@dataclass
class _Result:
    at_bounds: tuple[str, ...]
    patient_motion: np.ndarray
    drr_count: int = 10
    similarity_trace: list[float] = field(default_factory=lambda: [1.0])
    stopped: bool = False
    walk_hops: int = 0
    similarity: float = -1.0
    stages: tuple = ()
    parameters: tuple[str, ...] = ("tx", "ty", "rx", "ry", "rz")
    offsets: tuple[float, ...] = (30.0, 0.0, 0.0, 0.0, 0.0)
    geometry: CArm = field(default_factory=lambda: CArm.for_format(27.0, pixels=64))


@dataclass(frozen=True)
class _Inputs:
    volume: object = None
    views: tuple = ()
    initial_motion: np.ndarray = field(default_factory=lambda: np.eye(4))
    renderer: object = None


def test_the_box_walks_from_each_estimate_until_one_ends_inside(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(walk_module, "prepared_renderer", lambda volume, views, start, options: "prepared")
    starts = []

    def once(inputs: _Inputs) -> _Result:  # the estimate moves 30 mm per run; inside the box at the third
        starts.append(round(float(np.linalg.norm(inputs.initial_motion[:3, 3])), 9))
        return _Result(("tx",) if len(starts) < 3 else (), np.eye(4))

    result = walk_module.walk_from_bounds(once, _Inputs(), RegistrationOptions())
    # each run starts where the last one ended, with its own preparation
    assert starts == [0.0, 30.0, 60.0]
    assert result.walk_hops == 2 and result.at_bounds == ()
    assert result.drr_count == 30 and len(result.similarity_trace) == 3  # every run's cost is counted
    # at most walk_hops restarts: still at the bounds after them, the result says so
    starts.clear()
    capped = walk_module.walk_from_bounds(once, _Inputs(), RegistrationOptions(start=StartOptions(walk_hops=1)))
    assert starts == [0.0, 30.0] and capped.walk_hops == 1 and capped.at_bounds == ("tx",)


def test_a_walked_estimate_is_never_applied_automatically() -> None:
    walked = _Result((), np.eye(4), walk_hops=2)
    assert "beyond the search box" in veto(walked) and "2 times" in veto(walked)
    assert veto(_Result((), np.eye(4))) is None


def test_bad_start_options() -> None:
    with pytest.raises(ValueError, match="walk_hops must be >= 1"):
        StartOptions(walk_hops=0)


def test_a_patient_beyond_the_search_box_is_registered_by_walking() -> None:
    """A moment of the capture study's quick run, 40 mm from the machine-based pose (beyond the
    box's 30 mm), seen by both planes: the first search ends on the box's wall, the walk goes on
    to the true pose. Not every patient this far is captured (validate capture measures the
    rate); this one is, and its estimate is withheld for the user to check."""
    from registration.core.assess import assess
    from registration.studies.biplane import _offset_motion, case_preparations, case_views, study_volume
    from registration.studies.capture import CaptureConfig, capture_tasks

    task = next(t for t in capture_tasks(CaptureConfig.quick_config(seed=0)) if "translation/40mm-0deg/r1" in t.case_id)
    case = task.case
    volume = study_volume(case.ct_path, case.phantom_seed, case.volume_format_cm, case.volume_voxels)
    truth = _offset_motion(case)
    views, _ = case_views(case, volume, truth)
    pair, _ = case_preparations(case, volume, views, RegistrationOptions())
    fixed = register(volume, list(views), seed=case.seed, truth=truth, renderer=pair.renderer,
                     options=RegistrationOptions(start=False))  # fmt: skip
    assert fixed.at_bounds and not fixed.residual.success_total and fixed.walk_hops == 0
    # the walk alone (the shifted start, which also captures this moment, is tested on its own)
    walk_only = RegistrationOptions(start=StartOptions(shift_mm=None))
    walked = register(volume, list(views), seed=case.seed, truth=truth, renderer=pair.renderer, options=walk_only)
    assert walked.walk_hops >= 1 and walked.at_bounds == ()
    # the biplane criterion (CONVENTIONS §6: 3-D residual at the iso-center < 1 mm, < 3 deg)
    assert walked.residual.success_total, walked.residual
    assert walked.drr_count > fixed.drr_count and walked.to_dict()["walk_hops"] == walked.walk_hops
    decision = assess(walked, list(views), pair)
    assert not decision.applied and "beyond the search box" in decision.reason
