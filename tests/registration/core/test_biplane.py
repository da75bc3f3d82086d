"""Biplane registration (CONVENTIONS §6): tz from two views, the combined measure, the one-view
path unchanged, the search space and the polish's budget."""

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from registration.core.anneal import POLISH_XTOL, Schedule, polish
from registration.core.geometry import CArm, offsets_to_matrix
from registration.core.register import Level, RegistrationOptions, register
from registration.core.search import FIVE_PARAMETERS, SIX_PARAMETERS, SearchSpace

#: A short search on 64-96 px images from a 64^3 volume: enough to register the test's views,
#: small enough for a few seconds per registration on a loaded machine.
_SCHEDULE = Schedule(step=(3.0, 3.0, 1.5, 1.5, 1.5), stages=8, moves_per_stage=8, probes=4)
FAST = RegistrationOptions(
    levels=(Level(48, 1, _SCHEDULE, restarts=2), Level(96, 0, Schedule(step=(1.0, 1.0, 0.5, 0.5, 0.5), stages=4))),
    polish_evaluations=40,
    polish_image_px=96,
    polish_volume_level=0,
    support_margin_mm=(10.0, 5.0, 4.0),
)


@pytest.fixture(scope="module")
def scene():
    from registration.sim.phantom import make_head_phantom, registration_volume
    from registration.sim.xray import simulate_xray

    volume = registration_volume(make_head_phantom(seed=0, contrast=True), 27.0, voxels=64)
    anatomy = make_head_phantom(seed=0, contrast=False)
    plane_a = CArm.for_format(27.0, pixels=96)
    plane_b = CArm(primary_deg=90.0, sid_mm=1150.0, sod_mm=760.0, rows=96, cols=96, pixel_mm=(2.5, 2.5))
    # 8 mm along plane A's beam (tz) plus a little in-plane motion and rotation.
    truth = offsets_to_matrix((2.0, -1.0, 8.0, 1.0, 0.0, 2.0), plane_a)
    views = [simulate_xray(anatomy, g, motion=truth, kind="exposure", seed=n) for n, g in enumerate((plane_a, plane_b))]
    return volume, views, truth


def test_tz_recovered_from_two_views_where_one_cannot(scene):
    volume, views, truth = scene
    single = register(volume, views[0], truth=truth, seed=3, options=replace(FAST, depth_correction=False))
    corrected = register(volume, views[0], truth=truth, seed=3, options=FAST)
    levels = []
    both = register(volume, views, truth=truth, seed=3, options=FAST, callback=lambda p: levels.append(p.level))
    # One view without the depth correction keeps tz: its estimate stays ~8 mm off along the beam
    # (the paper's five parameters).
    assert single.parameters == FIVE_PARAMETERS
    assert single.residual.outofplane_mm > 6.0, single.residual
    # The depth correction reads tz from magnification only, on this coarse 64^3 volume partly
    # (~4 mm of the 8 here): better than none, but not the 1 mm that a second view gives.
    assert corrected.parameters == FIVE_PARAMETERS and corrected.depth_tz_mm is not None
    assert corrected.residual.outofplane_mm < single.residual.outofplane_mm, corrected.residual
    assert corrected.residual.outofplane_mm > 1.0, corrected.residual
    # Two views see it: the whole 3-D residual at the iso-center is below the 1 mm criterion
    # (a 64^3 volume of 2.8 mm voxels and 2.5 mm pixels: well below a voxel, not the study's 0.3 mm).
    assert both.parameters == SIX_PARAMETERS
    assert both.residual.translation_mm < 1.0, both.residual
    assert both.residual.outofplane_mm < 0.8, both.residual
    assert both.residual.rotation_deg < 1.5, both.residual
    assert both.success  # the 3-D criterion, since tz was optimised
    # Two DRRs per evaluation.
    assert both.drr_count % 2 == 0
    # The planes' captures (level 0; agreeing here, so no pair capture), the pair's coarse polish
    # on the capture level's images (1), then the polish (2), in that order.
    assert sorted(set(levels)) == [0, 1, 2] and levels == sorted(levels)
    d = both.to_dict()
    assert set(d["offsets"]) == set(SIX_PARAMETERS) and len(d["views"]) == 2


def test_combined_measure_is_the_mean_of_the_planes(scene):
    from registration.core.drr import DRRRenderer
    from registration.core.problem import LevelProblem
    from registration.core.similarity import gradient_difference

    volume, views, truth = scene
    renderer = DRRRenderer(volume, levels=2)
    problem = LevelProblem.prepare(renderer, tuple(views), image_px=48, volume_level=1, motion=truth, margin_mm=None)
    evaluator = problem.evaluator()
    motion = offsets_to_matrix((1.0, 0.0, 3.0, 0.0, 1.0, 0.0), views[0].geometry)
    parts = evaluator.per_view(motion)
    assert evaluator.similarity(motion) == pytest.approx(np.mean(parts), rel=1e-12)
    # Each part is the plain gradient difference of that plane's DRR against its image.
    for n, (view, part) in enumerate(zip(problem.views, parts, strict=True)):
        drr = renderer.render(view.geometry, motion, level=1, mask=view.mask)
        image = views[n].downsample(views[n].geometry.cols // view.geometry.cols)
        assert part == pytest.approx(gradient_difference(drr, image.image, view.mask), rel=1e-9)
    # Threads get their own scratch: two evaluators agree and do not disturb each other.
    other = problem.evaluator(parallel=False)
    assert other.similarity(motion) == pytest.approx(evaluator.similarity(motion), rel=1e-6)


def test_planes_weighted_by_the_share_of_their_field_they_compare(scene):
    """With the field-share weights each plane's GD counts for the share of its field inside the
    volume's support (its definition, counted here from the masks), and a registration's pair
    levels use them by default."""
    from registration.core.drr import DRRRenderer
    from registration.core.problem import LevelProblem, support_mask
    from registration.core.register.plan import Run

    volume, views, truth = scene
    renderer = DRRRenderer(volume, levels=2)
    kwargs = dict(image_px=48, volume_level=1, motion=truth, margin_mm=15.0)
    plain = LevelProblem.prepare(renderer, tuple(views), **kwargs)
    weighted = LevelProblem.prepare(renderer, tuple(views), **kwargs, field_share_weights=True)
    assert plain.weights is None
    shares = []
    for view in weighted.views:
        field = views[len(shares)].downsample(views[len(shares)].geometry.cols // view.geometry.cols).mask
        inside = field & support_mask(volume, view.geometry, truth, 15.0)
        shares.append(inside.sum() / field.sum())
    assert weighted.weights == pytest.approx(shares, rel=1e-12)
    # a 15 mm margin inside a 64^3 volume's cylinder leaves the planes different shares: the
    # weights then differ from the plain mean's
    assert 0.05 < min(shares) < max(shares) - 0.01 < 0.99
    motion = offsets_to_matrix((1.0, 0.0, 3.0, 0.0, 1.0, 0.0), views[0].geometry)
    parts = weighted.evaluator().per_view(motion)
    expected = (shares[0] * parts[0] + shares[1] * parts[1]) / (shares[0] + shares[1])
    assert weighted.evaluator().similarity(motion) == pytest.approx(expected, rel=1e-12)
    assert plain.evaluator().similarity(motion) == pytest.approx(np.mean(parts), rel=1e-12)
    # one view: nothing to weigh
    assert LevelProblem.prepare(renderer, tuple(views[:1]), **kwargs, field_share_weights=True).weights is None
    # the registration's levels of two views are weighted unless the option turns it off
    run = Run(SimpleNamespace(renderer=renderer, views=tuple(views)), RegistrationOptions(), None, None, None)
    assert run.problem(48, 1, 15.0, truth).weights == pytest.approx(shares, rel=1e-12)
    off = RegistrationOptions(biplane=replace(RegistrationOptions().biplane, field_share_weights=False))
    assert (
        Run(SimpleNamespace(renderer=renderer, views=tuple(views)), off, None, None, None)
        .problem(48, 1, 15.0, truth)
        .weights
        is None
    )


def test_one_view_path_is_the_five_parameter_search(scene):
    volume, views, truth = scene
    a = register(volume, views[0], truth=truth, seed=5, options=FAST)
    b = register(volume, [views[0]], truth=truth, seed=5, options=FAST)
    # A single XRayImage and a list of one are the same registration, bit for bit.
    np.testing.assert_array_equal(a.patient_motion, b.patient_motion)
    assert a.drr_count == b.drr_count and a.similarity == b.similarity  # (the trace interleaves threads)
    assert list(a.to_dict()["offsets"]) == list(FIVE_PARAMETERS) and "views" not in a.to_dict()


def test_search_space_maps_parameters_as_offsets_to_matrix():
    geometry = CArm.for_format(27.0, primary_deg=30.0, secondary_deg=-10.0)
    initial = offsets_to_matrix((1.0, 2.0, 3.0, 4.0, 5.0, 6.0), geometry)
    five = SearchSpace(geometry, initial, FIVE_PARAMETERS)
    six = SearchSpace(geometry, initial, SIX_PARAMETERS, bound_mm=20.0)
    x5 = np.array([1.5, -2.0, 0.3, -0.7, 2.0])
    # Bit for bit the old composition (the single-view results must not move).
    old = offsets_to_matrix([1.5, -2.0, 0.0, 0.3, -0.7, 2.0], geometry) @ initial
    np.testing.assert_array_equal(five.motion(x5), old)
    x6 = np.array([1.5, -2.0, 4.0, 0.3, -0.7, 2.0])
    np.testing.assert_array_equal(six.motion(x6), offsets_to_matrix(x6, geometry) @ initial)
    assert six.bounds.tolist()[2] == [-20.0, 20.0] and six.bounds.tolist()[3] == [-15.0, 15.0]
    np.testing.assert_array_equal(six.per_parameter((4.0, 4.0, 2.0, 2.0, 2.0)), [4.0, 4.0, 4.0, 2.0, 2.0, 2.0])
    with pytest.raises(ValueError, match="parameters"):
        SearchSpace(geometry, initial, ("tx", "tz"))


def test_polish_keeps_its_budget_and_stops_without_exceptions():
    calls = []

    def bowl(x):
        calls.append(x.copy())
        return float(np.sum((x - 0.3) ** 2))

    bounds = np.array([[-2.0, 2.0]] * 3)
    result = polish(bowl, np.zeros(3), bounds, step=[0.5, 0.5, 0.5], max_evaluations=25)
    # The budget counts evaluations after x0; Powell never gets more.
    assert len(calls) <= 26 and result.nfev == len(calls)
    assert result.fun <= bowl(np.zeros(3)) and result.fun == pytest.approx(np.sum((result.x - 0.3) ** 2))
    calls.clear()
    stopped = polish(bowl, np.zeros(3), bounds, step=[0.5] * 3, max_evaluations=60, callback=lambda s: s.nfev >= 5)
    # Stopped after the 5th evaluation: no more cost calls, the best point so far returned.
    assert len(calls) == 5 and stopped.message == "stopped by the callback"
    assert stopped.fun == min(float(np.sum((c - 0.3) ** 2)) for c in calls)


def test_cobyqa_polish_stays_in_its_bounds_and_budget_and_finds_a_bowls_minimum():
    calls = []

    def bowl(x):
        calls.append(x.copy())
        return float(np.sum((x - np.array([0.3, -0.4, 0.2, 0.1, -0.2])) ** 2 * np.array([1, 1, 4, 4, 4])))

    bounds = np.array([[-1.0, 1.0]] * 5)
    bounds[1] = [-0.3, 1.0]  # the minimum's -0.4 lies beyond: the polish ends on the bound
    result = polish(bowl, np.zeros(5), bounds, step=[0.5] * 5, max_evaluations=40, xtol=0.01, method="cobyqa")
    assert len(calls) <= 41 and result.nfev == len(calls)  # x0, then at most the budget
    assert all(np.all(c >= bounds[:, 0]) and np.all(c <= bounds[:, 1]) for c in calls)
    # a quadratic in five parameters: COBYQA's models are exact after ~21 points
    np.testing.assert_allclose(result.x, [0.3, -0.3, 0.2, 0.1, -0.2], atol=0.01)
    with pytest.raises(ValueError, match="method must be"):
        polish(bowl, np.zeros(5), bounds, step=[0.5] * 5, max_evaluations=5, method="bfgs")


def test_pair_polish_searches_near_its_start_and_a_range_wide_polish_does_not():
    from registration.core import register as reg
    from registration.core.register.build import polish_stages
    from registration.core.register.stages import run_polish

    geometry = CArm.for_format(27.0, pixels=64)
    six = SearchSpace(geometry, np.eye(4), SIX_PARAMETERS, 30.0, 15.0)
    optimum = np.array([0.4, -0.3, 0.6, 0.5, -0.4, 0.3])  # within a mm and a degree of the start
    start = np.array([0.1, 0.2, -0.3, 0.1, 0.2, -0.2])
    # A stand-in for the level's cost: a bowl with coupled parameters about the optimum and a
    # small ripple (gradient difference is rugged at the scale of a tenth of a pixel).
    a = np.random.default_rng(1).normal(size=(6, 6))
    hessian = np.eye(6) + 0.15 * (a + a.T)  # positive definite (eigenvalues 0.26-1.66)

    def bowl(x):
        return float((x - optimum) @ hessian @ (x - optimum) + 0.003 * np.sin(40.0 * x).sum())

    class Evaluator:
        drrs_per_evaluation = 2

        def __init__(self):
            self.points = []

        def similarity(self, motion):
            x = six.from_motion(motion)
            self.points.append(x)
            return -bowl(x)

    def run(pair, options, coarse=False):
        evaluator = Evaluator()
        problem = type("Problem", (), {"evaluator": lambda self, parallel=None: evaluator})()
        monitor = reg.Monitor(six, None, 0.0)
        stages = polish_stages(options, pair)  # the pair's: its coarse polish, then its polish
        budget = (stages[0] if coarse else stages[-1]).budget
        best = run_polish(problem, six, 1, start, budget, monitor)
        return np.array(evaluator.points), best, monitor.drr_count

    options = RegistrationOptions(polish_evaluations=45, pair_polish_evaluations=45, pair_polish_reach=(4.0, 3.0),
                                  pair_polish_xtol=0.1, pair_coarse_polish_evaluations=30,
                                  pair_coarse_polish_reach=(3.0, 2.0))  # fmt: skip
    points, pair_best, drrs = run(True, options)
    # Every point the pair's polish evaluates lies within its reach of the start (4 mm, 3 deg).
    reach = np.where(six.is_translation(), *options.pair_polish_reach)
    assert np.all(np.abs(points - start) <= reach + 1e-9)
    assert len(points) == 46 and drrs == 2 * len(points)  # the start and its budget, two views each
    # The coarse polish before it: its own budget and reach.
    points, _, _ = run(True, options, coarse=True)
    assert len(points) == 31
    assert np.all(np.abs(points - start) <= np.where(six.is_translation(), 3.0, 2.0) + 1e-9)
    # A single-plane polish (pair=False) over the whole search range (polish_reach None, the
    # default before the single-plane polish got its own reach): its line searches open 7 mm
    # out (fminbound's first points, 38 % into +- 30 mm from the ends).
    wide = replace(options, polish_reach=None, polish_xtol=POLISH_XTOL)
    points, single_best, _ = run(False, wide)
    assert len(points) == 46
    assert np.max(np.abs(points[:, 0] - start[0])) > 5.0
    # Same budget: the near search ends closer to the optimum (max error over the parameters:
    # 0.24 against 0.50 here) because fewer of its evaluations land far from it.
    pair_error, single_error = np.abs(pair_best.x - optimum).max(), np.abs(single_best.x - optimum).max()
    assert pair_error < 0.3 < single_error, (pair_error, single_error)


def _study_planes():
    """Plane A (27 cm, 512 px) and plane B (22 cm, 384 px) of the biplane study, near frontal/lateral."""
    from registration.sim.biplane import BiplaneSystem

    system = BiplaneSystem()
    return system.plane_a.nominal(8.0, -5.0), system.plane_b.nominal(97.0, 6.0)


def test_plane_estimates_combine_into_the_pose_both_planes_see():
    from registration.core.geometry import invert_rigid, rotation_angle_deg
    from registration.core.register import combine_plane_estimates, plane_disagreement

    plane_a, plane_b = _study_planes()
    initial = offsets_to_matrix((0.5, -1.0, 2.0, 0.0, 1.0, 0.0), plane_a)
    # 24 mm across plane B's beam, 15 mm along plane A's, rotated 6 degrees about a tilted axis.
    truth = offsets_to_matrix((-24.0, 4.0, 15.0, 3.0, -4.0, 2.5), plane_a) @ initial
    # What a perfect single-plane (five-parameter) capture of each plane returns: the truth,
    # but with the iso-center's displacement along its own beam kept at the initial pose's.
    estimates = []
    for g in (plane_a, plane_b):
        x = SearchSpace(g, initial, SIX_PARAMETERS).from_motion(truth)
        estimates.append(SearchSpace(g, initial, FIVE_PARAMETERS).motion(x[[0, 1, 3, 4, 5]]))
    combined = combine_plane_estimates(initial, tuple(estimates), (plane_a, plane_b))
    err = combined @ invert_rigid(truth)
    # Each plane's along-beam displacement comes from the other: exact to rounding (1e-9 mm).
    assert np.linalg.norm(err[:3, 3]) < 1e-9 and rotation_angle_deg(err) < 1e-9
    shared_mm, rotation_deg = plane_disagreement(tuple(estimates), (plane_a, plane_b))
    assert shared_mm < 1e-9 and rotation_deg < 1e-9
    # A capture that traded a rotation for a translation disagrees with the other plane by the
    # rotation (12 deg about plane A's v axis) and, across both beams, by the part of the
    # translation (30 mm along plane A's u axis) the axis across both beams sees.
    from registration.core.geometry import rigid, rotation_y

    u, v = plane_a.world_from_view[:3, 0], plane_a.world_from_view[:3, 1]
    moved = rigid(None, 30.0 * u) @ estimates[0]
    shared = np.cross(plane_a.direction, plane_b.direction)
    shared_mm, rotation_deg = plane_disagreement((moved, estimates[1]), (plane_a, plane_b))
    assert shared_mm == pytest.approx(30.0 * abs(u @ shared) / np.linalg.norm(shared), abs=1e-9)
    assert rotation_deg < 1e-9
    p = estimates[0][:3, :3] @ plane_a.isocenter_mm + estimates[0][:3, 3]  # where the iso-center went
    world_from_view = plane_a.world_from_view[:3, :3]
    turn = world_from_view @ rotation_y(12.0) @ world_from_view.T  # 12 deg about v
    turned = rigid(None, p) @ rigid(turn, None) @ rigid(None, -p) @ estimates[0]
    shared_mm, rotation_deg = plane_disagreement((turned, estimates[1]), (plane_a, plane_b))
    assert rotation_deg == pytest.approx(12.0, abs=1e-9) and shared_mm < 1e-9
    assert abs(v @ (turn @ v) - 1.0) < 1e-12  # (v is the rotation's axis)


def test_further_planes_are_compared_at_plane_a_resolution():
    from registration.core.problem import iso_pixel_mm, level_factor, matched_factor

    plane_a, plane_b = _study_planes()
    voxel_mm = 2.85  # the 27 cm 3DRA's quarter-resolution level (256^3 at 0.71 mm)
    for image_px in (64, 128):
        fa = level_factor(plane_a, image_px, voxel_mm)
        fb = matched_factor(plane_b, image_px, voxel_mm, iso_pixel_mm(plane_a, fa))
        # Never coarser than plane A's pixel at the iso-center, never finer than plane B's own rule,
        # and within one block of it (B's 0.57 mm pixels cannot match A's exactly).
        assert iso_pixel_mm(plane_b, fb) <= iso_pixel_mm(plane_a, fa) * (1 + 1e-6)
        assert fb >= level_factor(plane_b, image_px, voxel_mm)
        assert iso_pixel_mm(plane_b, fb + 1) > iso_pixel_mm(plane_a, fa) or plane_b.cols % (fb + 1)
        assert plane_b.cols // fb == plane_a.cols // fa  # here: the same pixels across (64 and 128)


def test_each_plane_captures_on_32_px_and_goes_on_at_64_px(scene):
    """Two views: each plane's capture runs on 32 px images of the eighth-resolution volume and
    each run goes on briefly at 64 px of the quarter-resolution volume before the planes are
    compared (the plan says so); a volume too small for level 3 keeps the 64 px capture alone."""
    from registration.core.register import registration_plan
    from registration.core.register.options import PLANE_CAPTURE_32, PLANE_REFINE_64
    from registration.sim.phantom import make_head_phantom, registration_volume

    plane_a, plane_b = _study_planes()
    volume = registration_volume(make_head_phantom(seed=0, contrast=True), 27.0, voxels=128)
    views = [_blank_view(g) for g in (plane_a, plane_b)]
    first = registration_plan(volume, views).describe().splitlines()[0]
    assert PLANE_CAPTURE_32.image_px == 32 and PLANE_CAPTURE_32.volume_level == 3
    assert PLANE_REFINE_64.image_px == 64 and PLANE_REFINE_64.volume_level == 2
    assert "each plane's own capture at 32 px, volume level 3, 2 runs per plane, each run then at 64 px, " \
           "volume level 2" in first, first  # fmt: skip
    small, small_views = scene[0], scene[1]  # 64^3: level 3 would be 8 voxels across
    first = registration_plan(small, small_views).describe().splitlines()[0]
    assert "each plane's own capture at 64 px, volume level 2, 2 runs per plane, up to" in first, first


def _blank_view(geometry: CArm):  # noqa: ANN202
    from registration.core.images import XRayImage

    shape = (geometry.rows, geometry.cols)
    return XRayImage(np.ones(shape, np.float32), np.ones(shape, bool), geometry)


def test_planes_whose_captures_disagree_are_said_and_their_flat_choice_withheld(scene):
    """Plane B sees the head 12 mm further cranial than plane A (two moments, not one): the
    planes' own captures cannot agree on what both see, the result says so, and the confidence
    weighs it against a flat peak."""
    from registration.core.assess import assess_on
    from registration.core.confidence import DEFAULT_RULE, Evidence
    from registration.core.drr import DRRRenderer
    from registration.core.geometry import rigid
    from registration.sim.phantom import make_head_phantom
    from registration.sim.xray import simulate_xray

    volume, views, truth = scene
    same = register(volume, views, options=FAST)
    assert not same.planes_disagreed and "planes_disagreed" not in same.to_dict()
    anatomy = make_head_phantom(seed=0, contrast=False)
    apart = simulate_xray(anatomy, views[1].geometry, motion=rigid(None, (0.0, 0.0, 12.0)) @ truth,
                          kind="exposure", seed=1)  # fmt: skip
    result = register(volume, [views[0], apart], options=FAST)
    assert result.planes_disagreed and result.to_dict()["planes_disagreed"] is True
    assert any(c.stage.endswith("(when the planes disagree)") for c in result.stages)
    renderer = DRRRenderer(volume, levels=3)
    assert assess_on(result, [views[0], apart], volume, renderer).evidence.planes_apart == 1.0
    assert assess_on(same, views, volume, renderer).evidence.planes_apart == 0.0
    # The rule at the evidence of the capture study's wrong two-view estimate (seed 0, 40 deg,
    # moment 2: margin 0.0015, capture runs apart, beam margin 0.0039): applied at 0.88 when the
    # planes' disagreement is not weighed, withheld with it; the least margin of a right estimate
    # whose planes disagreed there (0.0061) keeps its decision.
    recorded = Evidence(margin=0.0015, agreement=0.0, edges=0.26, beam_margin=0.0039)
    assert DEFAULT_RULE.assess(recorded).applied
    withheld = DEFAULT_RULE.assess(replace(recorded, planes_apart=1.0))
    assert not withheld.applied and "planes' own captures disagreed" in withheld.reason, withheld
    assert DEFAULT_RULE.assess(replace(recorded, margin=0.0061, planes_apart=1.0)).applied
