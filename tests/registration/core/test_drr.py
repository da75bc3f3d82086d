"""DRR renderer: analytic line integrals, fast against reference, motion, masks, bad input."""

import numpy as np
import pytest
from scipy import ndimage

from registration.core.drr import DRRRenderer, render_reference
from registration.core.geometry import CArm, offsets_to_matrix, rigid, rotation_z
from registration.core.volume import Volume, hu_to_mu_per_mm

MU_WATER = float(hu_to_mu_per_mm(0.0))  # attenuation per mm of the shapes below (0 HU)
SPACING = 2.0  # mm
N = 48  # voxels per axis: 96 mm cube, fast tests


def _grid(n: int = N, spacing: float = SPACING, supersample: int = 4):
    """Sub-voxel sample positions (world mm) for partial-volume voxelisation, shape (n, n, n, s^3)."""
    axis = (np.arange(n) - (n - 1) / 2.0) * spacing
    offs = ((np.arange(supersample) + 0.5) / supersample - 0.5) * spacing
    sub = (axis[:, None] + offs[None, :]).reshape(-1)
    z, y, x = np.meshgrid(sub, sub, sub, indexing="ij", sparse=True)
    return x, y, z, supersample


def _partial_volume(inside: np.ndarray, n: int, s: int) -> np.ndarray:
    """Fraction of each voxel inside the shape, from the supersampled indicator."""
    return inside.reshape(n, s, n, s, n, s).mean(axis=(1, 3, 5))


def _hu_from_fraction(fraction: np.ndarray) -> np.ndarray:
    """HU whose attenuation is ``fraction * MU_WATER`` (air -1000 -> 0, water 0 -> MU_WATER)."""
    return (fraction * 1000.0 - 1000.0).astype(np.float32)


@pytest.fixture(scope="module")
def sphere():
    center = np.array([6.0, -4.0, 5.0])
    radius = 30.0
    x, y, z, s = _grid()
    inside = (x - center[0]) ** 2 + (y - center[1]) ** 2 + (z - center[2]) ** 2 <= radius**2
    vol = Volume.from_grid(_hu_from_fraction(_partial_volume(inside, N, s)), SPACING)
    return vol, center, radius


@pytest.fixture(scope="module")
def box():
    lo = np.array([-25.0, -20.0, -30.0])
    hi = np.array([20.0, 26.0, 15.0])
    x, y, z, s = _grid()
    inside = (x >= lo[0]) & (x <= hi[0]) & (y >= lo[1]) & (y <= hi[1]) & (z >= lo[2]) & (z <= hi[2])
    vol = Volume.from_grid(_hu_from_fraction(_partial_volume(inside, N, s)), SPACING)
    return vol, lo, hi


@pytest.fixture(scope="module")
def smooth_volume():
    """A smooth random volume (fast and reference renderers integrate the same interpolant)."""
    rng = np.random.default_rng(3)
    data = ndimage.gaussian_filter(rng.normal(0.0, 1.0, (40, 40, 40)), 2.0)
    data = data / np.abs(data).max() * 800.0 + 200.0
    data[:2] = data[-2:] = -1000.0  # air at two faces: clipping to the non-air box
    return Volume.from_grid(data.astype(np.float32), 2.5, center_mm=(3.0, -2.0, 1.0))


def _small_view(primary=0.0, secondary=0.0, pixels=40, **kw) -> CArm:
    # 40 px x 3 mm at the detector = 120 mm, ~ 81 mm at the iso-center: covers the cubes.
    return CArm(primary, secondary, rows=pixels, cols=pixels, pixel_mm=(3.0, 3.0), **kw)


def _rays(geometry: CArm):
    """Source (3,) and unit directions (rows, cols, 3) of every pixel's ray, world mm."""
    rr, cc = np.mgrid[0 : geometry.rows, 0 : geometry.cols]
    targets = geometry.pixel_to_world(cc, rr)
    source = geometry.source_mm
    d = targets - source
    return source, d / np.linalg.norm(d, axis=-1, keepdims=True)


# ----------------------------------------------------------------------------------------------
# analytic line integrals
# ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("angles", [(0.0, 0.0), (35.0, -20.0), (90.0, 10.0)])
def test_sphere_chord_length(sphere, angles):
    vol, center, radius = sphere
    geometry = _small_view(*angles)
    drr = DRRRenderer(vol, levels=1).render(geometry)
    source, dirs = _rays(geometry)
    w = center - source
    along = dirs @ w
    dist = np.sqrt(np.maximum(w @ w - along**2, 0.0))
    expected = 2.0 * np.sqrt(np.maximum(radius**2 - dist**2, 0.0)) * MU_WATER
    # The voxelised sphere is the trilinear interpolant of partial-volume voxels: its surface
    # is blurred over ~1 voxel, symmetrically, so a chord keeps its length to a fraction of a
    # voxel at each end. A ray crossing the surface at a grazing angle stretches that blur by
    # r / sqrt(r^2 - d^2), hence the tolerance: 0.3 voxel of water times that factor, for rays
    # at least one voxel inside the rim.
    interior = dist < radius - SPACING
    assert interior.sum() > 100
    stretch = radius / np.sqrt(radius**2 - dist[interior] ** 2)
    err_mm = np.abs(drr - expected)[interior] / MU_WATER
    assert np.all(err_mm < 0.3 * SPACING * stretch), (err_mm / stretch).max()
    # Rays passing two voxels beyond the surface (partial volume + interpolation reach less)
    # see nothing.
    outside = dist > radius + 2 * SPACING
    assert outside.sum() > 100
    assert np.abs(drr[outside]).max() == 0.0


def test_box_path_length(box):
    vol, lo, hi = box
    geometry = _small_view(12.0, 8.0, detector_shift_mm=(1.5, -2.0, 0.0), detector_tilt_deg=(1.0, 0.0, 0.5))
    drr = DRRRenderer(vol, levels=1).render(geometry)
    source, dirs = _rays(geometry)
    # slab method, analytic
    with np.errstate(divide="ignore"):
        t0 = (lo - source) / dirs
        t1 = (hi - source) / dirs
    t_near = np.minimum(t0, t1).max(axis=-1)
    t_far = np.maximum(t0, t1).min(axis=-1)
    length = np.maximum(t_far - t_near, 0.0)
    expected = length * MU_WATER
    # Rays entering and leaving through opposite faces, two voxels away from every edge: a
    # partial-volume step across a face integrates exactly (to first order) under linear
    # interpolation. Tolerance: 0.2 voxel of water (second-order quadrature error of the
    # slice-by-slice sampling along oblique rays).
    shrink = 2.0 * SPACING
    entry = source + dirs * t_near[..., None]
    exit_ = source + dirs * t_far[..., None]

    def face_interior(p, axis):
        others = [a for a in range(3) if a != axis]
        on_face = np.isclose(p[..., axis], lo[axis]) | np.isclose(p[..., axis], hi[axis])
        within = [(p[..., a] > lo[a] + shrink) & (p[..., a] < hi[a] - shrink) for a in others]
        return on_face & within[0] & within[1]

    through = np.zeros(length.shape, bool)
    for axis in range(3):
        through |= face_interior(entry, axis) & face_interior(exit_, axis)
    good = (length > 0) & through
    assert good.sum() > 100
    err = np.abs(drr - expected)[good]
    assert err.max() < 0.2 * SPACING * MU_WATER, err.max() / MU_WATER
    # the total attenuation over the image is also right to a few percent (edges included)
    assert abs(drr.sum() / expected.sum() - 1.0) < 0.02


# ----------------------------------------------------------------------------------------------
# fast renderer against the reference
# ----------------------------------------------------------------------------------------------
VIEWS = {
    "frontal": _small_view(0.0, 0.0),
    "oblique": _small_view(30.0, 20.0),
    "lateral-caudal": _small_view(-90.0, -25.0),
    "steep-cranial": _small_view(10.0, 70.0),
    "shifted-tilted": _small_view(30.0, 20.0, detector_shift_mm=(2.0, 1.0, 0.0), detector_tilt_deg=(1.0, 0.0, 0.5)),
    "source-shifted": _small_view(-40.0, 5.0, source_shift_mm=(3.0, -2.0, 4.0)),
}


@pytest.mark.parametrize("name", list(VIEWS))
@pytest.mark.parametrize("with_motion", [False, True])
def test_fast_matches_reference(smooth_volume, name, with_motion):
    geometry = VIEWS[name]
    motion = offsets_to_matrix((4.0, -3.0, 6.0, 5.0, -4.0, 7.0), geometry) if with_motion else None
    fast = DRRRenderer(smooth_volume, levels=1).render(geometry, motion)
    ref = render_reference(smooth_volume, geometry, motion, step_mm=0.25 * 2.5)
    scale = float(ref.max())
    assert scale > 0.5
    # Both integrate the trilinear interpolant of the same voxels; they differ by quadrature:
    # the trapezoid rule over the slices of the dominant axis (the interpolant is not linear
    # between slices along an oblique ray) against the midpoint rule at 0.25 voxel. Measured
    # <= 0.3% (max) and <= 0.1% (mean) of the image maximum on this smooth volume.
    assert np.abs(fast - ref).max() < 0.005 * scale
    assert np.abs(fast - ref).mean() < 0.0015 * scale


def test_drr_continuous_in_pose(smooth_volume):
    """No jumps when a slice enters or leaves a ray (rays leave this volume through cut faces)."""
    geometry = VIEWS["oblique"]
    renderer = DRRRenderer(smooth_volume, levels=1)
    # translations along x move the cut faces x = const across the rays' entry points
    steps = [renderer.render(geometry, rigid(translation_mm=(0.05 * k, 0.0, 0.0))) for k in range(40)]
    change = np.abs(np.diff(np.stack(steps), axis=0)).max()
    # 0.05 mm moves a pixel's integral by <= 0.2% of the maximum here; dropping or adding a
    # whole slice of tissue when an entry point crosses a slice would jump by ~3%
    assert change < 0.005 * float(steps[0].max())


def test_parallel_and_serial_kernels_agree(smooth_volume, monkeypatch):
    from registration.core import drr

    geometry = VIEWS["shifted-tilted"].resized(64, 64)
    motion = offsets_to_matrix((2.0, 1.0, -1.0, 3.0, -2.0, 1.0), geometry)
    mask = geometry.field_mask()
    renderer = DRRRenderer(smooth_volume, levels=1)
    monkeypatch.setattr(drr, "_SERIAL_SAMPLES", 0)  # always parallel
    parallel = renderer.render(geometry, motion, mask=mask).copy()
    monkeypatch.setattr(drr, "_SERIAL_SAMPLES", 10**12)  # always serial
    serial = renderer.render(geometry, motion, mask=mask)
    # Two separately compiled kernels (fastmath lets each vectorise and reassociate the sums
    # its own way): float32 rounding differences only, ~1e-7 of the values; 1e-5 of the
    # largest line integral is still 100x below any real difference (one voxel's share).
    np.testing.assert_allclose(parallel, serial, rtol=0, atol=1e-5 * float(serial.max()))
    assert np.array_equal(parallel == 0, serial == 0)  # the same rays miss and are masked


def test_trilinear_marcher_matches_reference(smooth_volume):
    geometry = VIEWS["shifted-tilted"]
    motion = offsets_to_matrix((1.0, 2.0, -3.0, 2.0, 3.0, -4.0), geometry)
    fast = DRRRenderer(smooth_volume, levels=1, step_voxels=0.5).render(geometry, motion)
    ref = render_reference(smooth_volume, geometry, motion)
    # same midpoint rule at 0.5 against 0.5 voxel steps, different sample positions
    assert np.abs(fast - ref).max() < 0.01 * float(ref.max())


def test_coarse_level_approximates_full_resolution(smooth_volume):
    geometry = VIEWS["oblique"]
    renderer = DRRRenderer(smooth_volume, levels=2)
    assert renderer.n_levels == 2
    full = renderer.render(geometry, level=0)
    coarse = renderer.render(geometry, level=1)
    # 2x2x2 averaging smooths the volume: the line integrals agree to a few percent
    assert np.abs(full - coarse).max() < 0.05 * float(full.max())
    small = renderer.render(geometry.resized(20, 20), level=1)
    assert small.shape == (20, 20)


# ----------------------------------------------------------------------------------------------
# motion
# ----------------------------------------------------------------------------------------------
def _centroid(image: np.ndarray) -> np.ndarray:
    rr, cc = np.mgrid[0 : image.shape[0], 0 : image.shape[1]]
    w = image / image.sum()
    return np.array([(w * cc).sum(), (w * rr).sum()])


def test_translation_shifts_drr_by_projected_shift():
    # a small smooth blob: its projected centroid follows the projection of its center
    center = np.array([5.0, 3.0, -4.0])
    axis = (np.arange(N) - (N - 1) / 2.0) * SPACING
    z, y, x = np.meshgrid(axis, axis, axis, indexing="ij", sparse=True)
    blob = np.exp(-((x - center[0]) ** 2 + (y - center[1]) ** 2 + (z - center[2]) ** 2) / (2 * 4.0**2))
    vol = Volume.from_grid(_hu_from_fraction(blob), SPACING)
    geometry = _small_view(25.0, -15.0, pixels=48)
    renderer = DRRRenderer(vol, levels=1)
    still = renderer.render(geometry)
    t = np.array([7.0, -5.0, 9.0])
    moved = renderer.render(geometry, rigid(translation_mm=t))
    expected_shift = geometry.project(center + t) - geometry.project(center)
    # perspective makes the centroid of a 4 mm blob's shadow differ from the projected center
    # by far less than 0.1 px; the shift of the centroid equals the projected shift
    assert np.allclose(_centroid(moved) - _centroid(still), expected_shift, atol=0.1)
    assert np.linalg.norm(expected_shift) > 3.0


def test_motion_equals_moving_the_geometry(smooth_volume):
    """P_eff = P @ M: a rotation of the volume about the iso-center is the inverse rotation of the C-arm."""
    geometry = _small_view(20.0, 0.0)
    renderer = DRRRenderer(smooth_volume, levels=1)
    motion = rigid(rotation_z(15.0))  # rotation about the patient axis z, through the iso-center
    a = renderer.render(geometry, motion)
    b = renderer.render(geometry.with_angles(20.0 - 15.0, 0.0))
    assert np.allclose(a, b, atol=1e-4 * float(a.max()))


# ----------------------------------------------------------------------------------------------
# masks, buffers, count, bad input
# ----------------------------------------------------------------------------------------------
def test_mask_skips_pixels_and_count_increments(smooth_volume):
    geometry = _small_view(15.0, 5.0)
    renderer = DRRRenderer(smooth_volume, levels=2)
    assert renderer.count == 0
    full = renderer.render(geometry)
    mask = geometry.field_mask()
    out = np.full((geometry.rows, geometry.cols), 123.0, dtype=np.float32)
    masked = renderer.render(geometry, mask=mask, out=out)
    assert masked is out
    assert np.all(masked[~mask] == 0.0)
    assert np.array_equal(masked[mask], full[mask])
    renderer.render(geometry.resized(20, 20), level=1)
    assert renderer.count == 3


def test_a_level_added_shares_the_others(smooth_volume):
    geometry = _small_view(15.0, 5.0)
    renderer = DRRRenderer(smooth_volume, levels=2)
    finer = Volume(smooth_volume.data * 0.5, smooth_volume.index_to_world)  # another level 0 on the same grid
    added = renderer.with_levels({0: finer})
    # level 1 is the same object (not converted again) and renders the same DRR, bit for bit
    assert added.level_volume(1) is renderer.level_volume(1) and added.n_levels == 2
    small = geometry.resized(20, 20)
    assert np.array_equal(added.render(small, level=1), renderer.render(small, level=1))
    # level 0 is the new volume, as a renderer built on it renders it
    alone = DRRRenderer(smooth_volume, levels=[finer, None])
    assert np.array_equal(added.render(geometry, level=0), alone.render(geometry, level=0))
    assert added.count == 2 and renderer.count == 1  # counters of its own
    with pytest.raises(ValueError, match="levels"):
        renderer.with_levels({})


def test_empty_volume_renders_zero():
    vol = Volume.from_grid(np.full((8, 8, 8), -1000.0, np.float32), 5.0)
    assert np.all(DRRRenderer(vol, levels=1).render(_small_view(pixels=8)) == 0.0)


def test_volume_outside_the_beam_renders_zero(smooth_volume):
    far = Volume(smooth_volume.data, smooth_volume.index_to_world @ rigid(translation_mm=(0, 0, 900.0)))
    assert np.all(DRRRenderer(far, levels=1).render(_small_view()) == 0.0)


def test_bad_input(smooth_volume):
    renderer = DRRRenderer(smooth_volume, levels=2)
    geometry = _small_view()
    with pytest.raises(ValueError, match="mask shape"):
        renderer.render(geometry, mask=np.ones((5, 5), bool))
    with pytest.raises(ValueError, match="boolean"):
        renderer.render(geometry, mask=np.ones((40, 40), np.uint8))
    with pytest.raises(ValueError, match="rigid|rotation"):
        renderer.render(geometry, np.diag([2.0, 1.0, 1.0, 1.0]))
    with pytest.raises(ValueError, match="NaN"):
        renderer.render(geometry, np.full((4, 4), np.nan))
    with pytest.raises(ValueError, match="4x4"):
        renderer.render(geometry, np.eye(3))
    with pytest.raises(ValueError, match="level"):
        renderer.render(geometry, level=2)
    with pytest.raises(ValueError, match="level"):
        renderer.render(geometry, level=-1)
    with pytest.raises(ValueError, match="out"):
        renderer.render(geometry, out=np.empty((40, 40), np.float64))
    with pytest.raises(ValueError, match="CArm"):
        renderer.render("frontal")
    with pytest.raises(ValueError, match="levels"):
        DRRRenderer(smooth_volume, levels=0)
    with pytest.raises(ValueError, match="Volume"):
        DRRRenderer(np.zeros((8, 8, 8)))
    with pytest.raises(ValueError, match="step_mm"):
        render_reference(smooth_volume, geometry, step_mm=0.0)
    assert renderer.count == 0


@pytest.fixture(scope="module")
def islands_volume():
    """Smooth tissue in two islands with exact air (-1000 HU, zero attenuation) around and
    between them: the space the rays leap over."""
    rng = np.random.default_rng(5)
    data = ndimage.gaussian_filter(rng.normal(0.0, 1.0, (48, 48, 48)), 2.0)
    data = data / np.abs(data).max() * 800.0 + 200.0
    k, j, i = np.indices(data.shape)
    first = (i - 14) ** 2 + (j - 20) ** 2 + (k - 22) ** 2 < 11**2
    second = (i - 34) ** 2 + (j - 30) ** 2 + (k - 26) ** 2 < 9**2
    near = first | second
    data[~near] = -1000.0
    return Volume.from_grid(data.astype(np.float32), 2.5, center_mm=(3.0, -2.0, 1.0))


@pytest.mark.parametrize("name", list(VIEWS))
def test_leaping_over_empty_space_changes_nothing(islands_volume, name):
    """Rays that leap over the exact zeros give the same DRR as rays that sample every slice,
    with fewer samples."""
    geometry = VIEWS[name]
    motion = offsets_to_matrix((4.0, -3.0, 6.0, 5.0, -4.0, 7.0), geometry)
    leap = DRRRenderer(islands_volume, levels=1)
    every = DRRRenderer(islands_volume, levels=1, skip_empty=False)
    a, b = leap.render(geometry, motion), every.render(geometry, motion)
    scale = float(b.max())
    assert scale > 0.5
    # the samples left out are exact zeros: the same sums up to float32 rounding (~1e-6 relative)
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-5 * scale)
    assert np.array_equal(a == 0, b == 0)
    assert leap.samples_per_level[0] < 0.9 * every.samples_per_level[0]  # the air around the islands (measured 0.82)
    # (the every-slice kernel is the one test_fast_matches_reference holds to the reference)
