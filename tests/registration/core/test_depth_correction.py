"""The depth-corrected single-plane registration (RegistrationOptions.depth_correction) against
ground truth: an honest 256 px exposure of the phantom (simulated from the analytic head, not
by the renderer that scores it) against its 128^3 3DRA stand-in, the patient 20 mm off along
the beam, which a five-parameter search cannot see and absorbs as a magnification error."""

from dataclasses import replace

import numpy as np
import pytest

from registration.core.depth import scan_level
from registration.core.drr import DRRRenderer
from registration.core.geometry import CArm, offsets_to_matrix
from registration.core.register import RegistrationOptions, register

#: (tx, ty, tz, rx, ry, rz): in-plane and rotation offsets as Table I's T4, 20 mm along the beam
OFFSET = (3.0, -2.0, 20.0, 2.0, -1.0, 3.0)
# the correction alone: the rotation check after it has its own tests (test_rotation_check.py)
ON = RegistrationOptions(rotation_check=False)
OFF = RegistrationOptions(depth_correction=False)


@pytest.fixture(scope="module")
def scene():
    from registration.sim.phantom import make_head_phantom, registration_volume
    from registration.sim.xray import simulate_xray

    volume = registration_volume(make_head_phantom(seed=0, contrast=True), 27.0, voxels=128)
    geometry = CArm.for_format(27.0, pixels=256, primary_deg=20.0)
    out = {}
    for sign in (1.0, -1.0):
        o = np.array(OFFSET) * np.array([1, 1, sign, 1, 1, 1])
        truth = offsets_to_matrix(o, geometry)
        xray = simulate_xray(make_head_phantom(seed=0, contrast=False), geometry, motion=truth, kind="exposure", seed=1)
        out[sign] = (truth, xray)
    return volume, DRRRenderer(volume, levels=3), out


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_the_correction_removes_the_magnification_error(scene, sign):
    volume, renderer, cases = scene
    truth, xray = cases[sign]
    off = register(volume, xray, truth=truth, seed=0, renderer=renderer, options=OFF)
    on = register(volume, xray, truth=truth, seed=0, renderer=renderer, options=ON)
    # Without it tz stays at the initial pose, 20 mm off: a 2.7 % magnification error which the
    # in-plane fit absorbs at ~0.05 mm per mm (measured 1.25 mm toward the source, 1.16 mm away
    # from it): a near miss of the 1 mm criterion, as the clinical study's applied misses.
    assert off.depth_tz_mm is None and off.depth_moves_mm == ()
    assert off.residual.outofplane_mm == pytest.approx(20.0, abs=0.5)
    assert off.residual.inplane_mm > 0.8, off.residual
    # With it the scans move tz toward the truth (measured 18.3 and -19.9 mm of the 20) and the
    # in-plane error drops (measured 0.12 and 0.04 mm): 0.3 mm is this 27 cm / 256 px frame's
    # polish jitter (0.53 mm pixels at the iso-center) with room; the tz bound of 5 mm: the
    # scans are capped at three, each seeing half to all of what is left (the scan's measure is
    # shallow along the beam).
    assert on.depth_tz_mm is not None and abs(on.depth_tz_mm - 20.0 * sign) < 5.0, on.depth_moves_mm
    assert on.residual.outofplane_mm < 5.0, on.residual
    assert on.residual.inplane_mm < 0.3, on.residual
    assert on.residual.rotation_deg < 1.0, on.residual
    assert on.success and on.parameters == off.parameters
    # the correction's DRRs are counted: the same annealing (same seed), then its scans and
    # polishes (a first scan of <= 25 DRRs, two rescans of <= 13, <= 3 polishes of <= 61
    # evaluations: the budget and the start)
    budget = 25 + 2 * 13 + 3 * (ON.depth_polish_evaluations + 1)
    assert 0 < on.drr_count - off.drr_count <= budget


def test_the_estimate_holds_the_scanned_tz_beside_the_five_offsets(scene):
    volume, renderer, cases = scene
    truth, xray = cases[1.0]
    start = offsets_to_matrix((1.0, 0.5, 3.0, 0.5, 0.0, 1.0), xray.geometry)
    on = register(volume, xray, initial_motion=start, truth=truth, seed=0, renderer=renderer, options=ON)
    o = on.offsets
    six = (o[0], o[1], on.depth_tz_mm, o[2], o[3], o[4])
    # patient_motion = offsets_to_matrix((tx, ty, depth_tz_mm, rx, ry, rz)) @ initial_motion
    np.testing.assert_allclose(on.patient_motion, offsets_to_matrix(six, xray.geometry) @ start, atol=1e-9)
    d = on.to_dict()
    assert d["depth_tz_mm"] == on.depth_tz_mm and len(d["depth_moves_mm"]) == len(on.depth_moves_mm) >= 1
    assert list(d["offsets"]) == ["tx", "ty", "rx", "ry", "rz"]
    assert "depth_tz_mm" not in register(volume, xray, seed=0, renderer=renderer, options=OFF).to_dict()
    # deterministic
    again = register(volume, xray, initial_motion=start, seed=0, renderer=renderer, options=ON)
    np.testing.assert_array_equal(again.patient_motion, on.patient_motion)


def test_a_stopped_registration_is_not_corrected(scene):
    volume, renderer, cases = scene
    _, xray = cases[1.0]
    result = register(volume, xray, seed=0, renderer=renderer, options=ON, callback=lambda p: p.iteration >= 30)
    assert result.stopped and result.depth_tz_mm is None


def test_two_views_are_not_corrected(scene):
    """Biplane estimates all six parameters already: the option changes nothing there."""
    volume, renderer, cases = scene
    truth, xray = cases[1.0]
    g_b = CArm.for_format(27.0, pixels=128, primary_deg=-70.0)
    from registration.sim.phantom import make_head_phantom
    from registration.sim.xray import simulate_xray

    small = CArm.for_format(27.0, pixels=128, primary_deg=20.0)
    views = [
        simulate_xray(make_head_phantom(seed=0, contrast=False), g, motion=truth, kind="exposure", seed=2)
        for g in (small, g_b)
    ]
    fast = replace(ON, pair_coarse_polish_evaluations=10, pair_polish_evaluations=10)
    a = register(volume, views, seed=0, renderer=renderer, options=fast)
    b = register(volume, views, seed=0, renderer=renderer, options=replace(fast, depth_correction=False))
    assert a.depth_tz_mm is None and "tz" in a.parameters
    np.testing.assert_array_equal(a.patient_motion, b.patient_motion)
    assert a.drr_count == b.drr_count


def test_the_scan_level_is_chosen_in_millimetres(scene):
    volume, renderer, _ = scene
    sizes = [float(renderer.level_volume(k).spacing_mm.max()) for k in range(renderer.n_levels)]
    # the level whose voxel is nearest 1 mm (in ratio), and nearest 2 or 4 mm when asked
    for target in (1.0, 2.0 * sizes[0], 4.0 * sizes[0]):
        want = int(np.argmin([abs(np.log(s / target)) for s in sizes]))
        assert scan_level(renderer, target) == want
    # a renderer of prepared levels without level 0 (a CT prepared for a search): never level 0
    partial = DRRRenderer(volume, levels=[None, renderer.level_volume(1), renderer.level_volume(2)])
    assert scan_level(partial, 0.1) == 1
    with pytest.raises(ValueError):
        scan_level(renderer, 0.0)


def test_a_coarse_volume_is_prepared_with_its_level0_for_one_planes_scan(scene):
    """A 128^3 3DRA (2.1 M voxels): one view's preparation holds level 0, the volume's own grid,
    and the correction scans there (1 mm is nearer its 2.1 mm voxel than level 1's 4.2 mm);
    two views, no correction, or a limit below the volume's size: levels 1 and 2 only."""
    from registration.core.register.inputs import prepared_volume

    volume, _, cases = scene
    truth, xray = cases[1.0]
    prepared = prepared_volume(volume, (xray,), np.eye(4), ON)
    assert prepared.renderer.has_level(0) and scan_level(prepared.renderer) == 0
    # the volume's own grid, not resampled (its spacing to float32's precision)
    np.testing.assert_allclose(prepared.renderer.level_volume(0).spacing_mm, volume.spacing_mm, rtol=1e-6)
    b = replace(xray.geometry, primary_deg=xray.geometry.primary_deg + 90.0)
    two = (xray, replace(xray, geometry=b))
    for views, options in (
        (two, ON),
        ((xray,), OFF),
        ((xray,), replace(ON, depth=replace(ON.depth, level0_max_voxels=volume.data.size - 1))),
    ):
        prepared = prepared_volume(volume, views, np.eye(4), options)
        assert not prepared.renderer.has_level(0) and scan_level(prepared.renderer) == 1


def test_a_volume_too_coarse_to_see_magnification_is_not_corrected(scene):
    """48^3 over a 27 cm field (5.6 mm voxels, the app's PACS export): a 2.7 % magnification is
    below what it resolves, so the five-parameter estimate is left as it is."""
    from registration.sim.phantom import make_head_phantom, registration_volume

    _, _, cases = scene
    truth, xray = cases[1.0]
    coarse = registration_volume(make_head_phantom(seed=0, contrast=True), 27.0, voxels=48)
    renderer = DRRRenderer(coarse, levels=3)
    assert float(renderer.level_volume(scan_level(renderer)).spacing_mm.max()) > ON.depth_max_voxel_mm
    result = register(coarse, xray, truth=truth, seed=0, renderer=renderer, options=ON)
    assert result.depth_tz_mm is None and "depth_tz_mm" not in result.to_dict()


def test_bad_depth_options():
    for bad in (
        {"depth_rounds": 0},
        {"depth_move_mm": 0.0},
        {"depth_bound_mm": -1.0},
        {"depth_voxel_mm": float("nan")},
        {"depth_max_voxel_mm": 0.0},
        {"depth_image_px": 8},
        {"depth_polish_reach": (2.0, 0.0)},
        {"depth_polish_evaluations": 0},
        {"depth_level0_max_voxels": -1},
    ):
        with pytest.raises(ValueError):
            RegistrationOptions(**bad)


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_the_scan_before_the_polish_moves_tz_first(scene, sign):
    """The shipped order (a scan along the beam before the polish, then rescans, every move kept):
    the scan moves tz first, and the depth and the in-plane error are as good as the polish-first
    order's (its rays: the next test)."""
    volume, renderer, cases = scene
    truth, xray = cases[sign]
    first = register(volume, xray, truth=truth, seed=0, renderer=renderer, options=ON)
    after = replace(ON, depth=replace(ON.depth, scan_first=False, keep_small_moves=False))
    late = register(volume, xray, truth=truth, seed=0, renderer=renderer, options=after)
    names = [s.stage.split(" ")[0] for s in first.stages]
    assert names.index("scan") == names.index("polish") - 1, names
    assert "scan" not in [s.stage.split(" ")[0] for s in late.stages]
    # the scan before the polish moves tz most of the way (measured 11.1 and -11.9 mm of the 20)
    assert first.depth_moves_mm[0] * sign > 8.0, first.depth_moves_mm
    # the same tolerances as the polish-first order above (measured 18.7 / -20.5 mm; 0.16 / 0.06
    # mm in plane)
    assert abs(first.depth_tz_mm - 20.0 * sign) < 5.0 and first.residual.outofplane_mm < 5.0, first.residual
    assert first.residual.inplane_mm < 0.3 and first.residual.rotation_deg < 1.0, first.residual


def test_the_scan_before_the_polish_renders_less_over_both_directions(scene):
    """Rays after the annealing, the shipped order against the polish first, over the two cases
    (20 mm towards and away from the source): the polish no longer runs at the wrong depth."""
    volume, renderer, cases = scene
    after = replace(ON, depth=replace(ON.depth, scan_first=False, keep_small_moves=False))

    def rays(options):
        results = [register(volume, xray, truth=truth, seed=0, renderer=renderer, options=options)
                   for truth, xray in cases.values()]  # fmt: skip
        return sum(s.rays for r in results for s in r.stages if not s.stage.startswith("anneal"))

    first, late = rays(ON), rays(after)
    # deterministic on one machine, not across CPUs (float rounding moves a rescan): measured
    # 3.21 M against 5.56 M on one, 4.07 M against 5.58 M on another (one case alone went either
    # way there); at least 15 % fewer over both
    assert first < 0.85 * late, (first, late)


def test_a_scan_after_the_capture_level_moves_tz_before_the_finer_annealing(scene):
    """``scan_after_capture``: one more scan along the beam right after the capture level, its move
    recorded first; the estimate as good as the shipped order's (the same tolerances)."""
    volume, renderer, cases = scene
    truth, xray = cases[1.0]
    options = replace(ON, depth=replace(ON.depth, scan_after_capture=True))
    early = register(volume, xray, truth=truth, seed=0, renderer=renderer, options=options)
    names = [s.stage.split(" ")[0] for s in early.stages]
    assert names[:3] == ["anneal", "scan", "anneal"] and names.count("scan") == 2, names
    assert "after the capture" in early.stages[1].stage
    # the capture level's estimate is coarse, yet the first scan moves tz most of the way (measured 10.6 of 20 mm)
    assert early.depth_moves_mm[0] > 6.0, early.depth_moves_mm
    assert abs(early.depth_tz_mm - 20.0) < 5.0 and early.residual.outofplane_mm < 5.0, early.residual
    assert early.residual.inplane_mm < 0.3 and early.residual.rotation_deg < 1.0, early.residual


def test_a_far_start_scans_after_the_capture_and_every_search_reaches_further():
    """One view's search from an image shift of 25 mm or more (withheld whatever it finds) scans
    along the beam after the capture level too; every one-view search may walk tz to 40 mm, the
    bound that withholds an estimate stays 25 mm. Any other search keeps its options."""
    from registration.core.register import far_start

    base = RegistrationOptions()
    assert far_start(base, 1, 0.0) is base and far_start(base, 1, 24.9) is base
    assert far_start(base, 2, 40.0) is base  # two views see the depth
    off = replace(base, depth=replace(base.depth, far_start_mm=None))
    assert far_start(off, 1, 40.0) is off
    far = far_start(base, 1, 25.0).depth
    assert far.scan_after_capture and not base.depth.scan_after_capture
    assert far.walk_mm == base.depth.walk_mm == 40.0 and far.bound_mm == base.depth.bound_mm == 25.0
    assert replace(base.depth, reach_mm=None).walk_mm == 25.0
