"""The single-plane confidence probes against ground truth: the depth probe (the volume released
along the beam) and the out-of-plane rotation margin. One honest 128 px exposure of the phantom
(not made by the renderer that scores it) against its 128^3 3DRA stand-in."""

import numpy as np
import pytest

from registration.core.confidence import DEFAULT_RULE, ConfidenceRule, Evidence
from registration.core.depth import SCAN_STRIDE, depth_probe, depth_scan, high_pass
from registration.core.geometry import CArm, offsets_to_matrix
from registration.core.metrics import residuals
from registration.core.tracking import registration_evidence


@pytest.fixture(scope="module")
def scene():
    from registration.core.drr import DRRRenderer
    from registration.sim.phantom import make_head_phantom, registration_volume
    from registration.sim.xray import simulate_xray

    volume = registration_volume(make_head_phantom(seed=0, contrast=True), 27.0, voxels=128)
    geometry = CArm.for_format(27.0, pixels=128, primary_deg=20.0)
    xray = simulate_xray(make_head_phantom(seed=0, contrast=False), geometry, kind="exposure", seed=1)
    return volume, xray, DRRRenderer(volume, levels=3)


def test_depth_probe_finds_the_magnification_and_the_in_plane_error(scene):
    volume, xray, renderer = scene
    g = xray.geometry
    # a single-plane estimate 15 mm off along the beam whose in-plane part absorbed 0.9 mm of it
    wrong = offsets_to_matrix([0.9, 0.0, 15.0, 0.0, 0.0, 0.0], g)
    probe = depth_probe(renderer, xray, wrong)
    # measured 1.5 mm from the truth along the beam: the measure's optimum along the beam is
    # shallow (a 2.5 % magnification over 15 mm); 4 mm still tells 15 mm from none
    assert abs(probe.tz_mm - (-15.0)) < 4.0, probe
    # the probe's in-plane move is the estimate's in-plane error (0.9 mm; 0.3 mm: the tracking of
    # the same phantom at this level has 0.1-0.2 mm of jitter, twice that for a 6-parameter polish)
    assert abs(probe.shift_mm - 0.9) < 0.3, probe
    res = residuals(probe.motion, np.eye(4), g)
    assert res.inplane_mm < 0.3 and res.rotation_deg < 1.0, res
    assert probe.gain_relative > 0 and probe.drr_count > 0
    # same input, same outcome (Powell is deterministic)
    again = depth_probe(renderer, xray, wrong)
    np.testing.assert_array_equal(again.motion, probe.motion)
    # the rule withholds it, the magnification alone (this pose is off the five-parameter peak
    # too, which the margin sees) costing more than half the bias
    e = registration_evidence(volume, xray, wrong, renderer=renderer, depth=probe)
    assert e.depth_shift_mm == pytest.approx(probe.shift_mm)
    assert not DEFAULT_RULE.assess(e).applied
    assert DEFAULT_RULE.terms(e)["depth"] < -0.5 * DEFAULT_RULE.bias


def test_right_pose_is_left_where_it_is_and_applied(scene):
    volume, xray, renderer = scene
    probe = depth_probe(renderer, xray, np.eye(4))
    # at the truth the probe barely moves in the plane (0.3 mm: the level's jitter, see above)
    assert probe.shift_mm < 0.3 and abs(probe.tz_mm) < 5.0, probe
    e = registration_evidence(volume, xray, np.eye(4), renderer=renderer, depth=probe)
    assert DEFAULT_RULE.assess(e).applied, (e, DEFAULT_RULE.terms(e))


def test_depth_scan_finds_the_offset_along_the_beam(scene):
    volume, xray, renderer = scene
    g = xray.geometry
    at_truth = depth_scan(renderer, xray, np.eye(4))
    # the high-pass scale is the volume's voxel seen at the detector, in the level's pixels
    voxel_px = float(renderer.level_volume(0).spacing_mm.max()) * g.magnification / max(g.pixel_mm)
    assert at_truth.sigma_px == pytest.approx(voxel_px)
    assert at_truth.drr_count == len(at_truth.offsets_mm)
    # measured -2.8 mm at the truth, -10.8 / +19.2 mm from 15 mm either side (this 128 px frame's
    # pixel is 2.1 mm at the detector: the measure is shallow along the beam); 5 mm tells 15 mm
    # off from none, and the sign is right
    assert abs(at_truth.tz_mm) < 4.0, at_truth
    for tz in (15.0, -15.0):
        scan = depth_scan(renderer, xray, offsets_to_matrix([0.0, 0.0, tz, 0.0, 0.0, 0.0], g))
        assert abs(scan.tz_mm + tz) < 5.0 and np.sign(scan.tz_mm) == -np.sign(tz), (tz, scan)
    # deterministic
    assert depth_scan(renderer, xray, np.eye(4)).similarity == at_truth.similarity
    # the confidence's strided scan: fewer DRRs, the same peak (every offset it evaluates has
    # the full scan's value, bit for bit: the same DRR and measure)
    for tz in (0.0, 15.0, -15.0):
        motion = offsets_to_matrix([0.0, 0.0, tz, 0.0, 0.0, 0.0], g)
        full, strided = depth_scan(renderer, xray, motion), depth_scan(renderer, xray, motion, stride=SCAN_STRIDE)
        assert strided.tz_mm == full.tz_mm, (tz, full, strided)
        assert strided.drr_count < 0.5 * full.drr_count, (strided.drr_count, full.drr_count)  # here 8-10 of 25
        values = dict(zip(full.offsets_mm, full.similarity, strict=True))
        assert all(values[o] == v for o, v in zip(strided.offsets_mm, strided.similarity, strict=True))
        # asked only below -7 mm (the confidence's question): the same peak when it lies there
        # (the estimate 15 mm from the source peaks near -15 mm), a stop with fewer DRRs elsewhere
        stopping = depth_scan(renderer, xray, motion, stride=SCAN_STRIDE, below_mm=-7.0)
        if strided.tz_mm < -7.0:
            assert not stopping.stopped and stopping.tz_mm == strided.tz_mm
        else:
            assert stopping.stopped and stopping.tz_mm >= -7.0 and stopping.drr_count < strided.drr_count
    assert depth_scan(renderer, xray, offsets_to_matrix([0.0, 0.0, 15.0, 0.0, 0.0, 0.0], g), stride=SCAN_STRIDE,
                      below_mm=-7.0).tz_mm < -7.0  # fmt: skip


def test_strided_scan_climbs_to_the_peak_between_its_samples():
    from registration.core.depth import _scanned

    offsets = tuple(float(o) for o in range(-12, 13, 2))  # 13 offsets
    calls: list[float] = []

    def peaked_at(p: float):
        def at(x: float) -> float:
            calls.append(x)
            return -((x - p) ** 2)

        return at

    # a peak between the every-third samples (-12, -6, 0, 6, 12): found by climbing, neighbours kept
    got, values, stopped = _scanned(offsets, peaked_at(4.0), 3)
    assert not stopped and got[int(np.argmax(values))] == 4.0 and {2.0, 6.0} <= set(got)
    assert len(calls) == len(set(calls)) < len(offsets)  # nothing evaluated twice, fewer than all
    # a peak at the last offset (always sampled) and stride 1 (every offset, in order)
    assert _scanned(offsets, peaked_at(12.0), 3)[0][-2:] == (10.0, 12.0)
    assert _scanned(offsets, peaked_at(0.0), 1)[0] == offsets
    with pytest.raises(ValueError, match="stride"):
        _scanned(offsets, peaked_at(0.0), 0)


def test_scan_asked_only_below_an_offset_decides_as_the_strided_scan():
    """The stopping scan (``below_mm``) on 400 random curves with one to three peaks: wherever the
    strided scan's peak lies below the offset asked about, the same peak to the bit; elsewhere
    not below either, and no more than half a step (1 mm) under the strided scan's."""
    from registration.core.depth import SCAN_TZ_MM, _scanned, scan_peak_mm

    rng = np.random.default_rng(7)
    offsets = SCAN_TZ_MM
    x = np.asarray(offsets)
    below_seen = stops = 0
    calls_full = calls_stopping = 0
    for _ in range(400):
        k = rng.integers(1, 4)
        centres, widths, heights = rng.uniform(-30, 30, k), rng.uniform(2, 20, k), rng.uniform(0.2, 1.0, k)
        curve = (heights * np.exp(-0.5 * ((x[:, None] - centres) / widths) ** 2)).sum(1) + rng.normal(0, 1e-3, x.size)
        for below in (-7.0, -3.0, 5.0):
            calls: list[float] = []

            def at(o: float, calls=calls, curve=curve) -> float:
                calls.append(o)
                return float(curve[offsets.index(o)])

            full = scan_peak_mm(*_scanned(offsets, at, SCAN_STRIDE))
            n_full = len(calls)
            calls.clear()
            got, values, stopped = _scanned(offsets, at, SCAN_STRIDE, below)
            tz = scan_peak_mm(got, values, stopped)
            assert len(calls) == len(set(calls))  # nothing rendered twice
            if full < below:
                below_seen += 1
                assert not stopped and tz == full, (below, full, tz)
            else:
                assert not tz < below and full >= tz - 1.0, (below, full, tz)
            stops += stopped
            calls_full, calls_stopping = calls_full + n_full, calls_stopping + len(calls)
    # both branches exercised (measured 575 peaks below, 542 stops of 1,200 scans); fewer
    # evaluations even on curves whose peaks fall anywhere (measured 0.82 of the strided scan's)
    assert below_seen > 300 and stops > 300, (below_seen, stops)
    assert calls_stopping < 0.9 * calls_full, (calls_stopping, calls_full)
    with pytest.raises(ValueError, match="ascending"):
        _scanned(offsets[::-1], lambda o: 0.0, SCAN_STRIDE, -7.0)


def test_high_pass_removes_the_smooth_part_inside_the_field_only():
    yy, xx = np.mgrid[0:64, 0:64]
    mask = (xx - 32) ** 2 + (yy - 32) ** 2 < 28**2
    ramp = 0.05 * xx + 3.0  # smooth: a ramp is kept by a Gaussian, so it is removed...
    out = high_pass(np.where(mask, ramp, 100.0), mask, 2.0)
    inner = (xx - 32) ** 2 + (yy - 32) ** 2 < 18**2  # ...wherever the smoothing sees only the field
    assert np.abs(out[inner]).max() < 1e-6
    assert np.all(out[~mask] == 0.0)
    # the field's edge does not leak the 100 outside into it (normalised smoothing: 0.075 at the
    # edge, from the ramp's one-sided mean there; a leak of the outside would be ~50)
    assert np.abs(out[mask]).max() < 0.2


def test_rotation_margin_is_flat_off_the_out_of_plane_rotation(scene):
    volume, xray, renderer = scene
    g = xray.geometry
    at_truth = registration_evidence(volume, xray, np.eye(4), renderer=renderer)
    # 6 degrees about the view's x axis (out of plane): the 3-degree probes toward the truth
    # score better than the pose itself, the margin is below the rule's knee
    tilted = registration_evidence(volume, xray, offsets_to_matrix([0, 0, 0, 6.0, 0, 0], g), renderer=renderer)
    assert at_truth.rotation_margin > DEFAULT_RULE.rotation_margin_good, at_truth
    assert tilted.rotation_margin < 0.0 < at_truth.rotation_margin, (tilted, at_truth)


def test_rule_terms_are_hinges_with_reasons():
    rule = ConfidenceRule()
    base = Evidence(margin=0.01, edges=0.5)
    assert rule.terms(base) == {"margin": 0.0, "edges": 0.0}
    flat = Evidence(margin=0.01, edges=0.5, rotation_margin=rule.rotation_margin_good - 0.003)
    assert rule.terms(flat)["rotation_margin"] == pytest.approx(-rule.rotation_margin_weight * 0.003)
    assert "out-of-plane rotations" in rule.assess(flat).reason
    moved = Evidence(margin=0.01, edges=0.5, depth_shift_mm=rule.depth_free_mm + 0.5)
    assert rule.terms(moved)["depth"] == pytest.approx(-rule.depth_weight * 0.5)
    assert not rule.assess(moved).applied
    assert Evidence(depth_shift_mm=0.2, rotation_margin=0.004).to_dict()["depth_shift_mm"] == 0.2
    # the depth scan: one-sided, only a peak away from the source beyond the free mm costs
    pulled = Evidence(margin=0.01, edges=0.5, depth_scan_tz_mm=rule.scan_free_mm - 4.0)
    assert rule.terms(pulled)["depth_scan"] == pytest.approx(-rule.scan_weight * 4.0)
    assert not rule.assess(pulled).applied and "along the beam" in rule.assess(pulled).reason
    toward = Evidence(margin=0.01, edges=0.5, depth_scan_tz_mm=20.0)
    assert rule.terms(toward)["depth_scan"] == 0.0 and rule.assess(toward).applied


def test_the_measure_does_not_depend_on_where_its_buffers_lie(scene):
    """Same DRR, same value, from every evaluator (each has its own buffers, elsewhere in
    memory). The gradient difference once summed in the loop that stores the DRR's gradients:
    LLVM ran its vector code there only where a run-time check found the stores clear of the
    loads, else a scalar copy, and the two group a reassociated sum differently, so 2 of these
    24 poses gave two values 2e-16 apart (and the depth probe's Powell another path: the exact
    equality above failed about every other run)."""
    from registration.core.problem import LevelProblem

    volume, xray, renderer = scene
    g = xray.geometry
    problem = LevelProblem.prepare(renderer, (xray,), image_px=128, volume_level=1, motion=np.eye(4), margin_mm=4.0)
    rng = np.random.default_rng(0)
    poses = [offsets_to_matrix(list(rng.uniform(-2.0, 2.0, 6)), g) for _ in range(24)]
    evaluators = [problem.evaluator() for _ in range(24)]  # all alive: their buffers lie apart
    values = np.array([[e.similarity(q) for q in poses] for e in evaluators])
    assert (values == values[0]).all(), [len(set(column)) for column in values.T]


def test_the_confidence_probes_and_scans_only_an_estimate_not_corrected_along_the_beam(scene):
    from dataclasses import replace

    from registration.core.assess import assess_on, depth_corrected
    from registration.core.register import register

    volume, xray, renderer = scene
    result = register(volume, xray, seed=0, renderer=renderer)
    assert depth_corrected(result)  # one view: the registration scanned and moved its tz itself
    corrected = assess_on(result, xray, volume, renderer)
    # neither probed nor scanned along the beam: both terms changed no decision on corrected estimates
    assert corrected.depth_probe is None and corrected.evidence.depth_shift_mm is None
    assert corrected.depth_scan is None and corrected.evidence.depth_scan_tz_mm is None
    # the same estimate as if no correction had run (the option off): probed and scanned, both weighed
    uncorrected = assess_on(replace(result, depth_moves_mm=()), xray, volume, renderer)
    assert uncorrected.depth_probe is not None
    assert uncorrected.evidence.depth_shift_mm == pytest.approx(uncorrected.depth_probe.shift_mm)
    assert uncorrected.depth_scan is not None
    assert uncorrected.evidence.depth_scan_tz_mm == pytest.approx(uncorrected.depth_scan.tz_mm)
    # everything else is measured the same way
    assert uncorrected.evidence.margin == corrected.evidence.margin


@pytest.mark.parametrize("shape", [(128, 128), (48, 96), (9, 13)])
@pytest.mark.parametrize("sigma", [0.7, 2.5, 6.0])
def test_smooth_is_scipys_gaussian(shape, sigma):
    """The depth scans' smoothing is scipy's ``gaussian_filter`` (4-sigma kernel, reflected
    edges), also where the kernel is wider than the image; float64 rounding is the only
    difference allowed."""
    from scipy import ndimage

    from registration.core.depth import smooth

    image = np.random.default_rng(3).normal(size=shape)
    np.testing.assert_allclose(smooth(image, sigma), ndimage.gaussian_filter(image, sigma), rtol=0, atol=1e-12)
    mask = np.zeros(shape)
    mask[1:-1, 2:] = 1.0
    np.testing.assert_allclose(smooth(mask, sigma), ndimage.gaussian_filter(mask, sigma), rtol=0, atol=1e-12)


def test_the_far_look_sees_a_patient_far_along_the_beam_and_not_a_right_estimate(scene):
    from registration.core.depth import FAR_OFFSETS_MM, depth_far, scan_level

    _, xray, renderer = scene
    level = scan_level(renderer)
    right = depth_far(renderer, xray, np.eye(4), volume_level=level)
    assert right.scan.drr_count == len(FAR_OFFSETS_MM) == 17
    # measured -0.25 at the truth; the rule starts to weigh it at -0.006 (right estimates of the
    # far draws -0.011 and below): twice that still leaves room for a fourfold flatter peak
    assert right.gain < 2.0 * DEFAULT_RULE.far_free, right
    assert DEFAULT_RULE.terms(Evidence(margin=0.01, depth_far_gain=right.gain))["depth_far"] == 0.0
    # an estimate 60 mm toward the source: the truth lies in the far window, and the measure
    # there beats every pose within 24 mm (measured +0.27, best at -64 mm, and +0.20 from 60 mm
    # the other way, best at +52 mm: the far samples are 12 mm apart, so within 8 mm of the truth)
    far = depth_far(renderer, xray, offsets_to_matrix([0.0, 0.0, 60.0, 0.0, 0.0, 0.0], xray.geometry),
                    volume_level=level)  # fmt: skip
    assert far.gain > 0.0 and abs(far.far_tz_mm + 60.0) <= 8.0, far
    away = depth_far(renderer, xray, offsets_to_matrix([0.0, 0.0, -60.0, 0.0, 0.0, 0.0], xray.geometry),
                     volume_level=level)  # fmt: skip
    assert away.gain > 0.0 and abs(away.far_tz_mm - 60.0) <= 8.0, away
    withheld = DEFAULT_RULE.assess(Evidence(margin=0.01, edges=0.5, depth_far_gain=far.gain))
    assert not withheld.applied and "far along the beam" in withheld.reason
    with pytest.raises(ValueError, match="within and beyond"):
        depth_far(renderer, xray, np.eye(4), volume_level=level, offsets_mm=(-8.0, 0.0, 8.0))


def test_the_far_look_runs_only_for_an_applied_flat_estimate_whose_captures_disagree(scene):
    from dataclasses import replace

    from registration.core.assess import FAR_PROBE_BELOW_AGREEMENT, FAR_PROBE_BELOW_MARGIN, _depth_far, assess
    from registration.core.confidence import Assessment
    from registration.core.preparation import Preparation
    from registration.core.register import register

    volume, xray, _ = scene
    preparation = Preparation.of(volume, xray)
    result = register(volume, xray, seed=0, renderer=preparation.renderer)
    # the whole assessment: captures that agree, no look; a right estimate stays applied
    agreeing = assess(replace(result, capture_motions=[np.asarray(result.patient_motion)] * 4), xray, preparation)
    assert agreeing.applied and agreeing.evidence.agreement == 1.0 and agreeing.depth_far is None

    def decided(applied: bool = True, margin: float = 0.5 * FAR_PROBE_BELOW_MARGIN, agreement: float = 0.0):
        return Assessment(0.9 if applied else 0.1, applied, "", Evidence(margin=margin, agreement=agreement))

    from registration.core.depth import scan_level

    renderer, level = preparation.renderer, scan_level(preparation.renderer)

    def look(outcome: Assessment, rule=DEFAULT_RULE, of=result):  # noqa: ANN001, ANN202
        return _depth_far(of, (xray,), renderer, level, outcome, rule)

    looked = look(decided())
    assert looked is not None and looked.scan.drr_count == 17
    assert look(decided(margin=FAR_PROBE_BELOW_MARGIN)) is None
    assert look(decided(agreement=FAR_PROBE_BELOW_AGREEMENT)) is None
    assert look(decided(applied=False)) is None  # it cannot change the decision
    assert look(decided(), rule=replace(DEFAULT_RULE, far_weight=0.0)) is None
    # two views (six parameters) never look: the other view sees the depth
    assert look(decided(), of=replace(result, parameters=(*result.parameters, "tz"))) is None
    # the look at the right estimate leaves it to the other terms (its peak stands out)
    assert looked.gain < DEFAULT_RULE.far_free, looked
