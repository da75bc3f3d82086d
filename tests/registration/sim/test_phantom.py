"""The analytic head phantom: exact line integrals, painter semantics, tissues, the stand-in 3DRA."""

from __future__ import annotations

import math

import numpy as np
import pytest

from registration.core.geometry import CArm, offsets_to_matrix, rotation_x, rotation_z
from registration.core.volume import MU_WATER_PER_MM, format_grid, hu_to_mu_per_mm
from registration.sim.phantom import STAND_IN_LABEL, HeadPhantom, make_head_phantom, registration_volume
from registration.sim.phantom_kernels import HU_AIR
from registration.sim.phantom_shapes import PhantomBuilder


@pytest.fixture(scope="module")
def head() -> HeadPhantom:
    return make_head_phantom()


def _ball(radius: float, hu: float, *, hole: float | None = None) -> HeadPhantom:
    b = PhantomBuilder()
    b.paint(b.ellipsoid([0.0, 0.0, 0.0], radius), hu, "ball", "bone")
    if hole is not None:
        b.paint(b.ellipsoid([0.0, 0.0, 0.0], hole), HU_AIR, "ball", "air")
    return b.build()


def _mu(hu: float) -> float:
    return MU_WATER_PER_MM * (1.0 + hu / 1000.0)


def test_ray_that_misses_is_zero(head: HeadPhantom) -> None:
    # far from the head (its extent is ~ +-120 mm; the neck ends at z = -300)
    src = np.array([[500.0, 500.0, 500.0], [0.0, 0.0, 400.0]])
    dst = np.array([[500.0, -500.0, 500.0], [0.0, 300.0, 400.0]])
    assert np.all(head.line_integrals(src, dst) == 0.0)


def test_chord_through_a_ball_is_analytic() -> None:
    ball = _ball(20.0, 1000.0)
    d = np.array([0.0, 5.0, 12.0, 19.9])  # ray offsets from the center (mm)
    src = np.stack([np.full_like(d, -100.0), d, np.zeros_like(d)], axis=1)
    dst = src + [200.0, 0.0, 0.0]
    expected = 2.0 * np.sqrt(20.0**2 - d**2) * _mu(1000.0)
    # exact up to floating point: the chord is solved in closed form
    np.testing.assert_allclose(ball.line_integrals(src, dst), expected, rtol=1e-10, atol=1e-12)


def test_painting_air_inside_a_ball_leaves_a_hollow_shell() -> None:
    shell = _ball(20.0, 1000.0, hole=15.0)
    src = np.array([[-100.0, 0.0, 0.0]])
    expected = 2.0 * (20.0 - 15.0) * _mu(1000.0)  # the air core contributes nothing
    np.testing.assert_allclose(shell.line_integrals(src, src + [200.0, 0.0, 0.0]), [expected], rtol=1e-10)
    assert shell.hu_at([0.0, 0.0, 0.0]) == HU_AIR
    assert shell.hu_at([17.0, 0.0, 0.0]) == 1000.0


@pytest.mark.parametrize(
    ("src", "dst"),
    [
        ((0.0, 300.0, 0.0), (0.0, -300.0, 0.0)),  # frontal through the circle of Willis
        ((-300.0, 15.0, -36.0), (300.0, 20.0, -38.0)),  # lateral through petrous bones and ears
        ((-200.0, -200.0, -60.0), (150.0, 100.0, -40.0)),  # oblique through sinuses and face
        ((10.0, 20.0, 200.0), (-20.0, -30.0, -200.0)),  # vertex to neck through the spine
    ],
)
def test_line_integral_matches_fine_numeric_integration(head: HeadPhantom, src, dst) -> None:
    src_a, dst_a = np.asarray(src), np.asarray(dst)
    length = float(np.linalg.norm(dst_a - src_a))
    step = 0.005  # mm, midpoint rule
    n = int(length / step)
    t = (np.arange(n) + 0.5) / n
    pts = src_a + t[:, None] * (dst_a - src_a)
    numeric = float(hu_to_mu_per_mm(head.hu_at(pts)).astype(np.float64).sum() * length / n)
    exact = float(head.line_integrals(src_a[None], dst_a[None])[0])
    assert exact > 1.0  # the ray crosses the head
    # The midpoint rule errs by at most one step times the jump in mu at each boundary the
    # ray crosses (< 100 boundaries, jumps < 0.08 / mm): 100 * 0.005 * 0.08 = 0.04 worst
    # case; the errors have random signs, so the typical error is far smaller. The hu_at
    # float32 rounding adds < 1e-6 relative.
    assert abs(numeric - exact) < 0.01, (numeric, exact)


def test_motion_moves_the_phantom(head: HeadPhantom) -> None:
    geom = CArm.for_format(27, pixels=16)
    motion = offsets_to_matrix([4.0, -3.0, 2.0, 3.0, -2.0, 5.0], geom)
    rng = np.random.default_rng(1)
    src = rng.uniform(-200, 200, (50, 3)) + [0.0, 600.0, 0.0]
    dst = rng.uniform(-200, 200, (50, 3)) - [0.0, 600.0, 0.0]
    inv = np.linalg.inv(motion)
    moved = head.line_integrals(src, dst, motion)
    by_hand = head.line_integrals(src @ inv[:3, :3].T + inv[:3, 3], dst @ inv[:3, :3].T + inv[:3, 3])
    # the same computation on the same transformed rays: identical up to rounding
    np.testing.assert_allclose(moved, by_hand, rtol=1e-12, atol=1e-12)
    assert np.max(np.abs(moved - head.line_integrals(src, dst))) > 0.1


def test_common_source_binning_matches_unbinned(head: HeadPhantom) -> None:
    # an image's rays share one source and go through the binned fast path; the same segments
    # reversed start at distinct points and take the unbinned path: the integrals must agree
    geom = CArm.for_format(27, pixels=32, primary_deg=30.0, secondary_deg=-10.0)
    rr, cc = np.mgrid[0:32, 0:32]
    targets = geom.pixel_to_world(cc.ravel(), rr.ravel())
    src = np.broadcast_to(geom.source_mm, targets.shape)
    binned = head.line_integrals(src, targets)
    reversed_ = head.line_integrals(targets, src)
    assert binned.max() > 3.0
    # same chords, computed from the other end: equal to rounding
    np.testing.assert_allclose(binned, reversed_, rtol=1e-9, atol=1e-9)


def test_voxelize_a_ball_gives_its_hu_and_volume() -> None:
    ball = _ball(10.0, 1000.0)
    n = 32
    aff = np.diag([1.0, 1.0, 1.0, 1.0])
    aff[:3, 3] = -(n - 1) / 2.0
    vox = ball.voxelize((n, n, n), aff, supersample=4)
    c = n // 2
    assert vox[c, c, c] == pytest.approx(1000.0, abs=1e-3)  # well inside: exact
    assert vox[0, 0, 0] == pytest.approx(HU_AIR, abs=1e-3)  # far outside: exact
    # anti-aliasing keeps the mass: the box average along i is exact, the 4x4 supersampling
    # across j, k errs by a fraction of a percent on a 10-voxel radius
    volume = float(np.sum(vox - HU_AIR)) / 2000.0
    assert volume == pytest.approx(4.0 / 3.0 * math.pi * 10.0**3, rel=0.005)


@pytest.mark.parametrize("oblique", [False, True])
def test_voxelize_is_the_exact_average_of_its_lines(head: HeadPhantom, oblique: bool) -> None:
    n, spacing, ss = 24, 8.0, 2
    rot = rotation_z(25.0) @ rotation_x(-15.0) if oblique else np.eye(3)
    aff = np.eye(4)
    aff[:3, :3] = rot * spacing
    aff[:3, 3] = -aff[:3, :3] @ np.full(3, (n - 1) / 2.0)
    vox = head.voxelize((n, n, n), aff, supersample=ss)
    assert vox.min() >= HU_AIR - 1e-3  # painting never goes below air
    # A voxel is the mean over ss x ss lines (across j, k) of the HU averaged exactly along i;
    # mu is linear in HU above air, so each line's average follows from a line integral.
    rng = np.random.default_rng(0)
    idx = rng.integers(0, n, (300, 3)).astype(np.float64)  # (i, j, k)
    offsets = (np.arange(ss) + 0.5) / ss - 0.5
    expected = np.zeros(len(idx))
    for dj in offsets:
        for dk in offsets:
            lo = (idx + [-0.5, dj, dk]) @ aff[:3, :3].T + aff[:3, 3]
            hi = lo + aff[:3, 0]
            mu_mean = head.line_integrals(lo, hi) / spacing
            expected += (mu_mean / MU_WATER_PER_MM - 1.0) * 1000.0 / ss**2
    ii = idx.astype(int)
    got = vox[ii[:, 2], ii[:, 1], ii[:, 0]]
    # float32 output and float64 sums of up to a few thousand HU: < 0.01 HU apart
    np.testing.assert_allclose(got, expected, atol=0.01)
    assert np.ptp(got) > 1000  # the sample holds bone and air, not only one tissue


def test_tissue_values(head: HeadPhantom) -> None:
    # a vertical probe down from the vertex: scalp, outer table, diploe, inner table, brain
    vault = head.hu_at(np.stack([np.zeros(80), np.full(80, 5.0), 108.0 - np.arange(80) * 0.25], 1))
    assert vault.max() > 1500  # cortical tables
    assert np.any((vault > 500) & (vault < 700))  # diploe between them
    assert np.any(np.abs(vault - 40.0) < 1)  # scalp
    maxillary = head.hu_at([[29.0, -57.0, -50.0], [-29.0, -57.0, -50.0]])
    assert np.all(maxillary < -800)  # air in the maxillary sinuses
    assert head.hu_at([0.0, -14.0, -41.0]) < -800  # sphenoid sinus
    brain = head.hu_at([[30.0, 20.0, 40.0], [-35.0, -30.0, 30.0]])
    assert np.all((brain >= 30) & (brain <= 40))
    ica, _ = head.path("ica_l")
    assert np.all(head.hu_at(ica) > 300)  # contrast-filled lumen
    assert head.hu_at(head.aneurysm[0]) > 300
    plain = make_head_phantom(contrast=False)
    assert np.all(np.abs(plain.hu_at(ica) - 40.0) < 1)  # blood without contrast
    assert head.hu_at([0.0, 0.0, 250.0]) == HU_AIR


def test_head_size(head: HeadPhantom) -> None:
    def extent(direction: list[float], through: list[float]) -> float:
        t = np.arange(-200.0, 200.0, 0.5)
        pts = np.asarray(through) + t[:, None] * np.asarray(direction)
        inside = t[head.hu_at(pts) > HU_AIR]
        return float(inside.max() - inside.min())

    # ~150 mm left-right, ~190 mm front-back (forehead to occiput), ~220 mm vertex to chin;
    # 0.5 mm probe steps, anatomical sizes within ~5 %
    assert extent([1.0, 0.0, 0.0], [0.0, 5.0, 18.0]) == pytest.approx(150.0, rel=0.05)
    assert extent([0.0, 1.0, 0.0], [0.0, 0.0, 18.0]) == pytest.approx(190.0, rel=0.05)
    z = np.arange(-200.0, 200.0, 0.5)
    top = z[head.hu_at(np.stack([np.zeros_like(z), np.full_like(z, 5.0), z], 1)) > HU_AIR].max()
    # the chin, in front of the neck (which runs on to z = -300 behind y = -46)
    bottom = z[head.hu_at(np.stack([np.zeros_like(z), np.full_like(z, -75.0), z], 1)) > HU_AIR].min()
    assert top - bottom == pytest.approx(220.0, rel=0.05)


def test_vessels_and_centerline(head: HeadPhantom) -> None:
    pts = head.vessel_centerline_mm()
    assert pts.shape[1] == 3 and len(pts) > 500
    assert np.all(head.vessel_mask_at(pts))
    assert np.linalg.norm(pts, axis=1).min() < 20  # the circle of Willis is near the iso-center
    assert not head.vessel_mask_at([0.0, 0.0, 60.0])
    center, radius = head.aneurysm
    assert 3.0 <= radius <= 4.0
    assert head.vessel_mask_at(center)


def test_seeds_and_facial_structures(head: HeadPhantom) -> None:
    again = make_head_phantom(seed=0)
    np.testing.assert_array_equal(again.hu, head.hu)
    other = make_head_phantom(seed=3)
    geom = CArm.for_format(48, pixels=32, primary_deg=90.0)
    rr, cc = np.mgrid[0:32, 0:32]
    targets = geom.pixel_to_world(cc.ravel(), rr.ravel())
    a = head.line_integrals(geom.source_mm, targets)
    b = other.line_integrals(geom.source_mm, targets)
    assert np.mean(np.abs(a - b)) > 0.05  # the variant differs ...
    assert abs(b.sum() - a.sum()) / a.sum() < 0.15  # ... but is the same kind of head (~3 % sizes)
    plain = make_head_phantom(facial=False)
    tooth = [0.0, -79.0 + 0.05**2 * 70 + 3.0, -79.0]
    assert head.hu_at(tooth) > 2000  # enamel
    assert plain.hu_at(tooth) < 100


def test_bad_input_raises(head: HeadPhantom) -> None:
    with pytest.raises(ValueError, match="finite"):
        head.line_integrals([[np.nan, 0.0, 0.0]], [[0.0, 0.0, 0.0]])
    with pytest.raises(ValueError, match="shape"):
        head.line_integrals([[0.0, 0.0]], [[0.0, 0.0]])
    with pytest.raises(ValueError, match="4x4"):
        head.line_integrals([[0.0, 0.0, 100.0]], [[0.0, 0.0, -100.0]], motion=np.eye(3))
    with pytest.raises(ValueError, match="rigid"):
        head.line_integrals([[0.0, 0.0, 100.0]], [[0.0, 0.0, -100.0]], motion=np.diag([2.0, 1, 1, 1]))
    with pytest.raises(ValueError, match="shape"):
        head.voxelize((4, 4), np.eye(4))
    with pytest.raises(ValueError, match="seed"):
        make_head_phantom(seed=-1)
    with pytest.raises(ValueError, match="volume_format_cm"):
        registration_volume(head, 0.0, voxels=16, cache=False)


def test_registration_volume_is_labelled_stand_in(head: HeadPhantom) -> None:
    vol = registration_volume(head, 27.0, voxels=32, cache=False)
    spacing, axis = format_grid(27.0, voxels=32)
    assert vol.label == STAND_IN_LABEL
    assert vol.shape == (32, 32, 32)
    np.testing.assert_allclose(vol.spacing_mm, spacing)
    np.testing.assert_allclose(vol.center_mm, [0.0, 0.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(vol.world_corners_mm()[0], [axis[0]] * 3)
    assert vol.data.max() > 1000  # bone survives the smoothing
    # same parameters, same noise
    np.testing.assert_array_equal(vol.data, registration_volume(head, 27.0, voxels=32, cache=False).data)
    other = registration_volume(head, 27.0, voxels=32, seed=1, cache=False)
    noise = float(np.std(other.data - vol.data)) / math.sqrt(2.0)
    assert 15.0 < noise < 25.0  # STAND_IN_NOISE_HU = 20 HU


def test_registration_volume_cache_round_trip(head: HeadPhantom, tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("ROADMAP3D_CACHE", str(tmp_path))
    first = registration_volume(head, 27.0, voxels=16)
    assert len(list(tmp_path.glob("*.npz"))) == 1
    again = registration_volume(head, 27.0, voxels=16)  # from the cache
    np.testing.assert_array_equal(first.data, again.data)
    registration_volume(head, 27.0, voxels=16, seed=1)  # another key, another entry
    assert len(list(tmp_path.glob("*.npz"))) == 2


def test_vessel_tips_are_closed(head: HeadPhantom) -> None:
    # A centerline ends exactly on its vessel's end cap; the lumen is a closed set, so the tip
    # and points a rounding error beyond it (1e-9 mm, far below POINT_TOLERANCE_MM = 1e-6 mm)
    # are inside on every machine, while 0.05 mm beyond the cap (well above the tolerance, well
    # below a voxel) is outside.
    for name in ("ica_r", "ica_l"):
        pts, _radius = head.path(name)
        for tip, before in ((pts[-1], pts[-2]), (pts[0], pts[1])):
            out = (tip - before) / np.linalg.norm(tip - before)
            assert head.vessel_mask_at(tip + 1e-9 * out)
    names = [p[0] for p in head.paths]
    ends = []
    for name in names:
        pts, _ = head.path(name)
        ends.append((pts[-1], (pts[-1] - pts[-2]) / np.linalg.norm(pts[-1] - pts[-2])))
    outside = [head.vessel_mask_at(p + 0.05 * d) for p, d in ends]
    assert sum(outside) < len(ends)  # most free tips end there (a few run into another artery)
