"""Estimating the C-arm's source-image distance with the pose (an uncalibrated system)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from registration.core.geometry import CArm
from registration.core.intrinsics import refine_geometry, with_intrinsics


def test_with_intrinsics_magnifies_and_shifts_as_a_pinhole_does() -> None:
    g = CArm(primary_deg=30.0, secondary_deg=-10.0, rows=256, cols=256, pixel_mm=(1.5, 1.5))
    points = np.array([[0.0, 0.0, 0.0], [40.0, -25.0, 10.0], [-30.0, 60.0, -20.0]])
    centre = g.project(np.zeros(3))
    longer = with_intrinsics(g, 1.05, (0.0, 0.0))
    # 5 % more source-image distance: every projection 5 % further from the principal point
    np.testing.assert_allclose(longer.project(points) - centre, 1.05 * (g.project(points) - centre), atol=1e-9)
    # the detector moved by +8 columns and -3 rows: the same world points land 8 columns lower and 3 rows higher
    moved = with_intrinsics(g, 1.0, (8.0, -3.0))
    np.testing.assert_allclose(moved.project(points) - g.project(points), [[-8.0, 3.0]] * 3, atol=1e-9)
    assert longer.sod_mm == g.sod_mm and longer.sid_mm == pytest.approx(1.05 * g.sid_mm)


def test_one_view_is_refused_with_the_reason() -> None:
    from registration.sim.phantom import make_head_phantom
    from registration.sim.xray import simulate_xray

    geometry = CArm.for_format(27.0, pixels=64)
    view = simulate_xray(make_head_phantom(), geometry, kind="fluoro", seed=0)
    with pytest.raises(ValueError, match="one view cannot tell its source-image distance from the depth"):
        refine_geometry(None, [view], np.eye(4))  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="cannot estimate \\['focal'\\]"):
        refine_geometry(None, [view, view], np.eye(4), estimate=("focal",))  # type: ignore[arg-type]


def test_a_five_percent_sid_error_is_estimated_with_two_planes() -> None:
    """The capture study's first quick moment, imaged with each plane's true geometry and
    registered on files whose source-image distance is 5 % short: the registration misses by
    millimetres, the refinement finds the distances and the pose."""
    from registration.core.metrics import residuals
    from registration.core.register import RegistrationOptions, register
    from registration.studies.biplane import (
        BiplaneConfig,
        _offset_motion,
        biplane_tasks,
        case_preparations,
        case_views,
        study_volume,
    )

    case = biplane_tasks(replace(BiplaneConfig.quick_config(seed=0), registrations_per_patient=1))[0].case
    volume = study_volume(None, case.phantom_seed, case.volume_format_cm, case.volume_voxels)
    truth = _offset_motion(case)
    views, _ = case_views(case, volume, truth)
    nominal = [replace(v, geometry=with_intrinsics(v.geometry, 1 / 1.05, (0.0, 0.0))) for v in views]
    pair, _ = case_preparations(case, volume, nominal, RegistrationOptions())
    plain = register(volume, nominal, truth=truth, seed=case.seed, renderer=pair.renderer)
    assert not plain.residual.success_total  # 2.5 mm off at this revision: the wrong distance shows
    found = refine_geometry(pair.renderer, nominal, plain.patient_motion, estimate=("sid",))
    res = residuals(found.patient_motion, truth, nominal[0].geometry, None, optimizes_tz=True)
    # the biplane criterion (CONVENTIONS §6)
    assert res.success_total, res
    # the true distances are 5 % longer than the files say; measured +5.5 % (plane A) and +5.7 %
    # (plane B) on this moment: within 1 % (the images' own bent geometry is not the refinement's)
    for view in found.intrinsics:
        assert view.sid_change == pytest.approx(0.05, abs=0.01)
    assert found.similarity > found.similarity_before and found.to_dict()["estimated"] == ["sid"]


def test_the_public_estimate_refuses_one_view_with_the_reason() -> None:
    import registration

    ex = registration.load_example(pixels=64)
    result = registration.register(ex.volume, ex.image)
    with pytest.raises(ValueError, match="one view cannot tell its source-image distance from the depth"):
        registration.estimate_geometry(ex.volume, [ex.image], result)


def test_views_of_one_detector_share_one_set_of_intrinsics() -> None:
    """``shared``: the parameter vector holds the pose and one detector's intrinsics, and every
    view is given those; per view (two planes) each has its own."""
    from registration.core.intrinsics import _Parameters

    shared, own = _Parameters(3, True, True, shared=True), _Parameters(3, True, True)
    assert shared.size == 6 + 3 and own.size == 6 + 3 * 3
    x = np.arange(shared.size, dtype=np.float64)
    pose, per_view = shared.unpack(x)
    np.testing.assert_array_equal(pose, x[:6])
    assert len(per_view) == 3 and all(sid == pytest.approx(1.06) for sid, _ in per_view)  # 6 % of the nominal
    assert all(np.array_equal(shift, [7.0, 8.0]) for _, shift in per_view)
    assert len(shared.bounds(4.0, 3.0, 0.1, 20.0)) == shared.size
    _, apart = own.unpack(np.arange(own.size, dtype=np.float64))
    assert [sid for sid, _ in apart] == pytest.approx([1.06, 1.09, 1.12])
