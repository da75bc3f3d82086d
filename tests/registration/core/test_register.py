"""End to end: Table I offsets recovered on a small, fast configuration; bad input."""

import numpy as np
import pytest

from registration.core.geometry import TABLE_I, CArm, offsets_to_matrix
from registration.core.register import RegistrationOptions, register
from registration.core.volume import Volume


@pytest.fixture(scope="module")
def setup():
    from registration.sim.phantom import make_head_phantom, registration_volume

    volume = registration_volume(make_head_phantom(seed=0, contrast=True), 27.0, voxels=128)
    anatomy = make_head_phantom(seed=0, contrast=False)
    return volume, anatomy


@pytest.mark.parametrize("offset", list(TABLE_I))
def test_table1_offsets_recovered(setup, offset):
    from registration.sim.xray import simulate_xray

    volume, anatomy = setup
    geometry = CArm.for_format(27.0, pixels=256)
    truth = offsets_to_matrix(TABLE_I[offset], geometry)
    xray = simulate_xray(anatomy, geometry, motion=truth, kind="fluoro", seed=1)
    result = register(volume, xray, seed=1, truth=truth, vessel_points_mm=anatomy.vessel_centerline_mm())
    # The paper's success criterion (single view: in-plane translation < 1 mm, rotation < 3 deg).
    assert result.residual.inplane_mm < 1.0, result.residual
    assert result.residual.rotation_deg < 3.0, result.residual
    assert result.success
    assert result.drr_count > 50 and len(result.similarity_trace) > 50
    d = result.to_dict()
    assert np.asarray(d["patient_motion"]).shape == (4, 4)


def test_same_seed_same_result(setup):
    from registration.sim.xray import simulate_xray

    volume, anatomy = setup
    geometry = CArm.for_format(27.0, pixels=128)
    truth = offsets_to_matrix(TABLE_I["T2"], geometry)
    xray = simulate_xray(anatomy, geometry, motion=truth, kind="exposure", seed=2)
    options = RegistrationOptions(polish_image_px=128, polish_volume_level=1)
    a = register(volume, xray, seed=5, options=options)
    b = register(volume, xray, seed=5, options=options)
    np.testing.assert_array_equal(a.patient_motion, b.patient_motion)
    assert a.drr_count == b.drr_count


def test_callback_stops_and_sees_progress(setup):
    from registration.sim.xray import simulate_xray

    volume, anatomy = setup
    geometry = CArm.for_format(27.0, pixels=128)
    xray = simulate_xray(anatomy, geometry, kind="fluoro", seed=0)
    seen = []

    def callback(progress):
        seen.append(progress)
        return progress.iteration >= 20

    result = register(volume, xray, callback=callback)
    assert result.stopped and len(seen) == 20
    assert seen[-1].drr_count == result.drr_count
    assert seen[-1].best_similarity >= seen[0].current_similarity - 1e-12
    assert seen[0].temperature > 0


def test_a_callback_that_raises_stops_every_capture_run(setup):
    """The exception reaches the caller, and the capture runs beside the one whose report raised
    stop at their next report instead of running to their ends (about 670 more calls before)."""
    from registration.sim.xray import simulate_xray

    volume, anatomy = setup
    geometry = CArm.for_format(27.0, pixels=128)
    xray = simulate_xray(anatomy, geometry, kind="fluoro", seed=0)
    calls = []

    def callback(progress):
        calls.append(progress.iteration)
        if len(calls) == 10:
            raise RuntimeError("the notebook's plot failed")

    with pytest.raises(RuntimeError, match="the notebook's plot failed"):
        register(volume, xray, callback=callback)
    # four capture runs share the monitor: the others may each be inside one report at most
    assert len(calls) <= 10 + 3, len(calls)


def test_bad_input(setup):
    from registration.sim.xray import simulate_xray

    volume, anatomy = setup
    data = np.zeros((8, 8, 8), np.float32)
    data[2, 3, 4] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        Volume.from_grid(data, 1.0)
    with pytest.raises(ValueError, match="spacing"):
        Volume.from_grid(np.zeros((8, 8, 8)), (1.0, 0.0, 1.0))
    with pytest.raises(ValueError, match="spacing"):
        Volume.from_grid(np.zeros((8, 8, 8)), -1.0)
    xray = simulate_xray(anatomy, CArm.for_format(27.0, pixels=64), seed=0)
    with pytest.raises(ValueError, match="rigid"):
        register(volume, xray, initial_motion=np.diag([1.0, 2.0, 1.0, 1.0]))
    with pytest.raises(ValueError, match="finite"):
        register(volume, xray, truth=np.full((4, 4), np.nan))


def test_support_mask_excludes_the_volume_outline():
    from registration.core.register import support_mask

    # A 100 mm cube (the reconstructable cylinder of radius 50 mm inside it) seen frontally:
    # at the iso-center the magnification is SID/SOD = 1.48, so the cylinder's outline lies
    # ~74 mm from the image center (the rays diverge, so a little more at the near side).
    volume = Volume.from_grid(np.zeros((50, 50, 50), np.float32), 2.0)
    geometry = CArm.for_format(48.0, pixels=96)  # 5 mm pixels
    x_mm = (np.arange(96) - 47.5) * 5.0
    mask = support_mask(volume, geometry, np.eye(4), 0.0)
    row = mask[48]
    inside = np.abs(x_mm) < 70.0  # clearly inside the outline
    outside = np.abs(x_mm) > 90.0  # beyond even the near side's magnification (1200/760 * 50 = 79)
    assert row[inside].all() and not row[outside].any()
    shrunk = support_mask(volume, geometry, np.eye(4), 20.0)
    assert shrunk.sum() < mask.sum()
    assert not shrunk[48][np.abs(x_mm) > 65.0].any()  # (50 - 20) mm * at most 1.6 magnification
    # A motion moves the support with the volume: 30 mm to the patient's left (+x = +u here).
    moved = support_mask(volume, geometry, offsets_to_matrix([30, 0, 0, 0, 0, 0], geometry), 0.0)
    assert moved[48][np.abs(x_mm - 30 * 1200 / 810) < 60.0].all()
    assert not moved[48][x_mm < -60.0].any()


def test_bad_options():
    from registration.core.anneal import Schedule
    from registration.core.register import Level

    with pytest.raises(ValueError, match="restarts"):
        RegistrationOptions(levels=(Level(64, 2, Schedule(), restarts=0),))
    with pytest.raises(ValueError, match="support_margin_mm"):
        RegistrationOptions(support_margin_mm=(1.0,))
    with pytest.raises(ValueError, match="image_px"):
        RegistrationOptions(levels=(Level(8, 0, Schedule()),))


def test_capture_runs_give_the_same_result_in_threads_or_in_turn(setup):
    from registration.sim.xray import simulate_xray

    volume, anatomy = setup
    geometry = CArm.for_format(27.0, pixels=128)
    truth = offsets_to_matrix(TABLE_I["T4"], geometry)
    xray = simulate_xray(anatomy, geometry, motion=truth, kind="fluoro", seed=4)
    threaded = register(volume, xray, seed=9, options=RegistrationOptions(threads=2))
    in_turn = register(volume, xray, seed=9, options=RegistrationOptions(threads=1))
    # Each capture run has its own random stream, so the order they run in cannot matter.
    np.testing.assert_array_equal(threaded.patient_motion, in_turn.patient_motion)
    assert threaded.drr_count == in_turn.drr_count


def test_progress_best_never_worsens_within_a_level(setup):
    from registration.sim.xray import simulate_xray

    volume, anatomy = setup
    geometry = CArm.for_format(27.0, pixels=128)
    xray = simulate_xray(anatomy, geometry, motion=offsets_to_matrix(TABLE_I["T1"], geometry), seed=0)
    seen = []
    register(volume, xray, callback=lambda p: seen.append(p) and False)
    # Two capture runs report side by side; the best shown spans both, so it only improves.
    capture = [p.best_similarity for p in seen if p.level == 0]
    assert len(capture) > 100
    assert all(b >= a for a, b in zip(capture, capture[1:], strict=False))


def test_polish_stays_within_its_reach_of_the_annealed_estimate(setup):
    """The polish searches the annealing's estimate +- polish_reach (mm, deg), not the whole
    search range: every point it evaluates lies there, and it spends its budget exactly."""
    from registration.core.search import SearchSpace
    from registration.sim.xray import simulate_xray

    volume, anatomy = setup
    geometry = CArm.for_format(27.0, pixels=128)
    truth = offsets_to_matrix(TABLE_I["T3"], geometry)
    xray = simulate_xray(anatomy, geometry, motion=truth, kind="fluoro", seed=3)
    options = RegistrationOptions()
    seen = []
    result = register(volume, xray, seed=3, truth=truth, options=options, callback=seen.append)
    # the stages run numbered: the annealing levels, the scan along the beam, then the polish
    assert [s.stage.split(" ")[0] for s in result.stages[len(options.levels) :][:2]] == ["scan", "polish"]
    polish_level = len(options.levels) + 1
    space = SearchSpace(geometry, np.eye(4))
    annealed = [p for p in seen if p.level == len(options.levels) - 1]
    polished = [p for p in seen if p.level == polish_level]
    assert len(polished) == options.polish_evaluations
    start = space.from_motion(annealed[-1].best_motion)
    half = np.where(space.is_translation(), *options.polish_reach)
    for p in polished:
        x = space.from_motion(p.current_motion)
        # 1e-9: the offsets come back from 4x4 motions (rounding)
        assert np.all(np.abs(x - start) <= half + 1e-9), (x, start)
    assert result.success


@pytest.mark.parametrize(
    ("pixels", "voxel_mm", "expected"),
    [(384, 2.85, 96), (384, 4.0, 64), (512, 2.85, 64), (512, 4.0, 64), (256, 4.0, 64), (768, 2.85, 96), (768, 4.0, 64)],
)
def test_refine_level_image_sizes(pixels, voxel_mm, expected):
    """The refine level compares about 64 px, but its pixels at the iso-center stay as fine as the
    quarter-resolution voxel (block sizes of powers of two up to it, dividing the image): the
    real CT's 4 mm voxels give 64 px at every size; the rotational run's 2.85 mm voxels give
    96 px of a 384 or 768 px image (blocks of 4 and 8), 64 px of a 512 px image (8)."""
    from registration.core.problem import level_factor

    refine = RegistrationOptions().levels[1]
    geometry = CArm.for_format(27.0, pixels=pixels)
    assert geometry.cols // level_factor(geometry, refine.image_px, voxel_mm) == expected


def test_each_stage_reports_its_cost(setup):
    """The result accounts per stage of the plan: DRRs, DRR pixels and seconds that add up."""
    from registration.core.register import registration_plan
    from registration.sim.xray import simulate_xray

    volume, anatomy = setup
    geometry = CArm.for_format(27.0, pixels=256)
    truth = offsets_to_matrix(TABLE_I["T2"], geometry)
    xray = simulate_xray(anatomy, geometry, motion=truth, kind="fluoro", seed=1)
    result = register(volume, xray, seed=1, truth=truth)
    planned = registration_plan(volume, xray).describe().splitlines()
    ran = [c.stage for c in result.stages]
    # every stage that ran is one of the plan's, in the plan's order (single plane: all of them run)
    assert [line.split(". ", 1)[1] for line in planned] == ran
    assert sum(c.drrs for c in result.stages) == result.drr_count  # every DRR charged to one stage
    assert all(c.rays >= c.drrs * 16 * 16 and c.seconds > 0 for c in result.stages)
    # every stage renders, but a rotation check whose screen the depth correction measured (its
    # first scan after the polish, after the scan before the polish, ended it)
    scans_before = int(RegistrationOptions().depth.scan_first)
    free = result.rotation_check.skipped and len(result.depth_moves_mm) == 1 + scans_before
    assert all(c.drrs > 0 or (free and c.stage.startswith("rotation check")) for c in result.stages)
    assert sum(c.seconds for c in result.stages) <= result.seconds + 1e-6
    assert result.to_dict()["stages"][0]["drrs"] == result.stages[0].drrs


def _support_mask_definition(volume, geometry, motion, margin_mm):  # noqa: ANN001, ANN202
    """The support mask in NumPy over all rays at once: the rays' box interval, clipped by the
    inscribed cylinder (the statement ``problem.support_mask`` compiles)."""
    rows, cols = np.mgrid[0 : geometry.rows, 0 : geometry.cols]
    targets = geometry.pixel_to_world(cols, rows).reshape(-1, 3)
    index_from_world = volume.index_from_world @ np.linalg.inv(np.asarray(motion, dtype=np.float64))
    src = index_from_world[:3, :3] @ geometry.source_mm + index_from_world[:3, 3]
    dirs = targets @ index_from_world[:3, :3].T + index_from_world[:3, 3] - src
    spacing = volume.spacing_mm
    src_mm, dirs_mm = src * spacing, dirs * spacing
    n = np.array(volume.shape[::-1], dtype=np.float64)
    lo, hi = np.full(3, margin_mm) - 0.5 * spacing, (n - 0.5) * spacing - margin_mm
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (lo - src_mm) / dirs_mm, (hi - src_mm) / dirs_mm
    near = np.nanmax(np.where(np.isfinite(t1), np.minimum(t1, t2), -np.inf), axis=1)
    far = np.nanmin(np.where(np.isfinite(t1), np.maximum(t1, t2), np.inf), axis=1)
    far[np.any((dirs_mm == 0) & ((src_mm < lo) | (src_mm > hi)), axis=1)] = -np.inf
    center = (n[:2] - 1) / 2.0 * spacing[:2]
    radius = min(n[0] * spacing[0], n[1] * spacing[1]) / 2.0 - margin_mm
    p, d = src_mm[:2] - center, dirs_mm[:, :2]
    a, b, c = np.sum(d * d, axis=1), 2.0 * d @ p, p @ p - radius * radius
    disc = b * b - 4 * a * c
    hit = (disc > 0) & (a > 0) & (radius > 0)
    root = np.sqrt(np.where(hit, disc, 0.0))
    safe_a = np.where(a > 0, a, 1.0)
    near = np.where(hit, np.maximum(near, (-b - root) / (2 * safe_a)), near)
    far = np.where(hit, np.minimum(far, (-b + root) / (2 * safe_a)), -np.inf)
    return (far > near).reshape(geometry.rows, geometry.cols)


def test_support_mask_equals_its_definition():
    """The compiled support mask is its NumPy statement pixel for pixel, on random grids (CT-like
    anisotropic ones too), views, motions and margins: every level's compared pixels depend on it."""
    from registration.core.problem import support_mask

    rng = np.random.default_rng(5)
    inside = 0
    for _ in range(60):
        shape = tuple(int(x) for x in rng.integers(8, 60, 3))
        affine = np.diag([*rng.uniform(0.4, 5.0, 3), 1.0])
        affine[:3, 3] = -affine[:3, :3] @ (np.array(shape[::-1]) / 2.0)
        volume = Volume(np.zeros(shape, np.float32), affine)
        geometry = CArm(float(rng.uniform(-90, 90)), float(rng.uniform(-40, 40)), rows=int(rng.choice([32, 64])),
                        cols=int(rng.choice([32, 48])), pixel_mm=(float(rng.uniform(0.5, 4.0)),) * 2)  # fmt: skip
        motion = offsets_to_matrix(rng.uniform(-30, 30, 6) * np.array([1, 1, 1, 0.5, 0.5, 0.5]), geometry)
        margin = float(rng.uniform(0.0, 10.0))
        got = support_mask(volume, geometry, motion, margin)
        np.testing.assert_array_equal(got, _support_mask_definition(volume, geometry, motion, margin))
        inside += int(got.sum())
    assert inside > 10_000  # the masks compared are not empty ones (measured: about a third of the pixels)
