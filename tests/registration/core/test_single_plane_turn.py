"""A single view's estimate that turns the head far from where its search started is shown, never
applied automatically; two views' estimates and small turns are assessed as before."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from registration.core.assess import SINGLE_PLANE_MAX_TURN_DEG, single_plane_turn_deg, veto
from registration.core.geometry import CArm
from registration.core.register import FIVE_PARAMETERS


@dataclass
class _Result:
    offsets: np.ndarray
    parameters: tuple[str, ...] = FIVE_PARAMETERS
    geometry: CArm = CArm.for_format(27.0, pixels=64, primary_deg=20.0, secondary_deg=-10.0)
    at_bounds: tuple[str, ...] = ()
    similarity: float = 1.0
    start_shift_mm: float = 0.0
    walk_hops: int = 0


def test_the_turn_is_the_rotation_of_the_estimated_offsets() -> None:
    # one axis: the turn is that angle exactly; the translation does not count
    assert single_plane_turn_deg(_Result(np.array([5.0, -3.0, 16.0, 0.0, 0.0]))) == pytest.approx(16.0, abs=1e-9)
    assert single_plane_turn_deg(_Result(np.array([0.0, 0.0, 0.0, 0.0, -9.0]))) == pytest.approx(9.0, abs=1e-9)
    # two views estimate all six parameters: no turn veto
    six = _Result(np.array([0.0, 0.0, 0.0, 30.0, 0.0, 0.0]), parameters=("tx", "ty", "tz", "rx", "ry", "rz"))
    assert single_plane_turn_deg(six) is None and veto(six) is None


def test_a_large_single_plane_turn_is_withheld_and_a_clinical_one_is_not() -> None:
    # the capture study's wrong applied estimate (seed 0, 40 deg offset): offsets as it found them,
    # a 16.3 deg turn; a right estimate at the clinical offsets' largest rotation (10 deg) plus
    # the success criterion's 3 deg stays below the limit
    wrong = _Result(np.array([0.94, -1.79, 11.87, 11.11, 3.05]))
    assert single_plane_turn_deg(wrong) == pytest.approx(16.3, abs=0.1)
    reason = veto(wrong)
    assert reason is not None and "turns the head 16 deg" in reason and "check it by eye" in reason
    assert veto(_Result(np.array([0.0, 0.0, 8.0, 5.0, 4.0]))) is None  # 10.2 deg
    assert SINGLE_PLANE_MAX_TURN_DEG == pytest.approx(13.0)
