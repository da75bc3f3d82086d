"""Preparing a volume for registration: crop to the field's reach, isotropic mm grids, cache."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy import ndimage

from registration.core import prepare
from registration.core.drr import DRRRenderer
from registration.core.geometry import CArm, offsets_to_matrix
from registration.core.prepare import Reach, level_spacing_mm, prepare_volume, resample_isotropic
from registration.core.volume import Volume

ISO = np.array([10.0, -6.0, 4.0])


def _blob_hu(points: np.ndarray) -> np.ndarray:
    """A smooth 'head' (ellipsoid with soft edges and inner texture) around ISO, HU."""
    d = (points - ISO) / np.array([70.0, 85.0, 75.0])
    r = np.sqrt((d**2).sum(-1))
    inside = 1.0 / (1.0 + np.exp((r - 1.0) * 120.0))  # a skin edge of ~1 mm
    texture = 300.0 * np.sin(points[..., 0] / 9.0) * np.cos(points[..., 1] / 11.0) * np.sin(points[..., 2] / 7.0)
    return (-1000.0 + inside * (1000.0 + 200.0 + texture)).astype(np.float32)


def _volume(spacing_xyz: tuple[float, float, float], extent_mm: float = 360.0, couch: bool = True) -> Volume:
    """The blob on a scanner-like grid: a large field of view, far tissue ('shoulders') below."""
    sp = np.asarray(spacing_xyz)
    n = np.round(extent_mm / sp).astype(int)
    axes = [ISO[a] + (np.arange(n[a]) - (n[a] - 1) / 2.0) * sp[a] for a in range(3)]
    z, y, x = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    hu = _blob_hu(np.stack([x, y, z], axis=-1))
    if couch:  # tissue far below the field ('shoulders', a couch): no ray of a small field meets it
        hu[(z < ISO[2] - 150.0) & (np.abs(x - ISO[0]) < 100.0) & (np.abs(y - ISO[1]) < 100.0)] = 40.0
    return Volume.from_grid(hu, tuple(sp), center_mm=ISO)


def _view(primary: float = 0.0, secondary: float = 0.0, fmt_cm: float = 27.0, pixels: int = 64) -> CArm:
    view = CArm.for_format(fmt_cm, pixels=pixels, primary_deg=primary, secondary_deg=secondary)
    return replace(view, isocenter_mm=tuple(ISO))


def test_level_spacing_is_the_pixel_at_the_isocenter() -> None:
    g = _view(fmt_cm=27.0, pixels=384)
    extent = prepare.field_extent_mm(g)
    # a 27 cm format covers 270 * SOD / SID = 182.25 mm at the iso-center
    assert extent == pytest.approx(270.0 * 810.0 / 1200.0)
    assert level_spacing_mm(extent, 2) == pytest.approx(extent / 64)  # the capture image's pixel
    assert level_spacing_mm(extent, 1) == pytest.approx(extent / 128)  # the polish image's pixel
    with pytest.raises(ValueError, match="level"):
        level_spacing_mm(extent, -1)


def test_scanner_grids_get_the_same_levels() -> None:
    """A 1.5 x 1.5 x 3 mm and a 1.5 x 1.5 x 5 mm scan of one anatomy: the slices do not change
    the (isotropic) grids, and the DRRs agree."""
    g = _view(20.0, -10.0, fmt_cm=27.0)
    a = prepare_volume(_volume((1.5, 1.5, 3.0), extent_mm=240.0), g, cache=False)
    b = prepare_volume(_volume((1.5, 1.5, 5.0), extent_mm=240.0), g, cache=False)
    assert a.spacing_mm == pytest.approx(b.spacing_mm)
    for lv in (1, 2):
        va, vb = a.levels[lv], b.levels[lv]
        assert np.allclose(va.spacing_mm, va.spacing_mm[0])  # isotropic
        # the crops agree to a probe block (of 4 mm: one 3 or 5 mm slice) at each end
        extent_a, extent_b = np.array(va.shape) * va.spacing_mm[0], np.array(vb.shape) * vb.spacing_mm[0]
        assert np.all(np.abs(extent_a - extent_b) <= 2 * 5.0 + 2 * va.spacing_mm[0])
    motion = offsets_to_matrix([3.0, -2.0, 0.0, 2.0, -1.0, 3.0], g)
    da = a.renderer.render(g, motion, level=2)
    db = b.renderer.render(g, motion, level=2)
    mask = g.field_mask()
    # The same smooth anatomy sampled by two scanners then resampled: the DRRs agree to a few
    # percent of their range (each scan's own interpolation error, mostly along the thick slices).
    assert np.abs(da - db)[mask].mean() < 0.03 * np.ptp(da[mask])


def test_crop_keeps_every_ray_the_search_can_see() -> None:
    """DRRs of the cropped volume equal the whole volume's inside the field, for motions within
    the reach; the crop removes the far tissue."""
    vol = _volume((2.0, 2.0, 2.0), extent_mm=320.0, couch=True)
    g = _view(30.0, 0.0, fmt_cm=15.0)  # 101 mm at the iso-center: the "couch" is out of reach
    reach = Reach.of_search(10.0, 4.0)
    lo, hi = prepare.needed_box(vol, [g], reach, margin_mm=4.0)
    cropped = prepare._crop(vol, lo, hi)
    assert np.prod(cropped.shape) < 0.5 * np.prod(vol.shape)
    full, cut = DRRRenderer(vol, levels=1), DRRRenderer(cropped, levels=1)
    rng = np.random.default_rng(1)
    mask = g.field_mask()
    for _ in range(4):
        offsets = np.concatenate([rng.uniform(-1, 1, 3) * 10.0 / np.sqrt(3), rng.uniform(-1, 1, 3) * 4.0 / np.sqrt(3)])
        m = offsets_to_matrix(offsets, g)
        # same voxels along every ray that meets tissue: float32 rounding only
        np.testing.assert_allclose(cut.render(g, m)[mask], full.render(g, m)[mask], rtol=1e-5, atol=1e-4)


def test_a_coarse_volume_keeps_its_own_pyramid() -> None:
    """A volume coarser than the field's level 0 (here 64 voxels across the field) is not
    resampled: level 0 holds its voxels, level 1 their 2^3 block averages."""
    g = _view(fmt_cm=15.0)
    extent = prepare.field_extent_mm(g)
    rng = np.random.default_rng(0)
    data = ndimage.gaussian_filter(rng.normal(0.0, 300.0, (64, 64, 64)), 1.5).astype(np.float32)
    vol = Volume.from_grid(data, extent / 64, center_mm=ISO)  # tissue everywhere
    prep = prepare_volume(vol, g, levels=(0, 1), cache=False)
    np.testing.assert_array_equal(prep.levels[0].data, vol.data)
    np.testing.assert_allclose(prep.levels[1].data, vol.downsample(2).data)


def test_crop_drops_tissue_out_of_reach_and_what_a_scanner_adds() -> None:
    """The cost follows the anatomy in the field: a larger field of view with more tissue far
    away (a couch, shoulders) gives the same prepared levels."""
    g = _view(0.0, 0.0, fmt_cm=27.0)
    reach = Reach(10.0, 4.0)
    small = prepare_volume(_volume((3.0, 3.0, 3.0), extent_mm=240.0, couch=False), g, reach=reach, cache=False)
    large = prepare_volume(_volume((3.0, 3.0, 3.0), extent_mm=480.0, couch=True), g, reach=reach, cache=False)
    assert small.voxels_per_level[0] is None and large.voxels_per_level[0] is None  # level 0 is not needed
    # the same anatomy in the field: the same grids to a probe block (4 mm) at each face
    for a, b in zip(small.levels[1:], large.levels[1:], strict=True):
        assert np.all(np.abs(np.array(a.shape) - np.array(b.shape)) * a.spacing_mm[0] <= 2 * 4.0 + a.spacing_mm[0])
    assert large.summary()["source_voxels"] > 8 * small.summary()["source_voxels"] / 1.5


def test_resample_is_exact_for_linear_fields() -> None:
    """Trilinear resampling reproduces a linear function exactly (smoothing keeps it too),
    away from the faces where the smoothing sees the edge."""
    k, j, i = np.meshgrid(np.arange(30), np.arange(40), np.arange(50), indexing="ij")
    affine = np.diag([1.0, 1.2, 3.0, 1.0])
    affine[:3, 3] = (-20.0, 5.0, -40.0)
    vol = Volume((2.0 * i + 3.0 * j - 5.0 * k).astype(np.float32), affine)

    def world_value(p: np.ndarray) -> np.ndarray:
        idx = (p - affine[:3, 3]) / np.diag(affine)[:3]
        return 2.0 * idx[..., 0] + 3.0 * idx[..., 1] - 5.0 * idx[..., 2]

    out = resample_isotropic(vol, 2.0)
    assert np.allclose(out.spacing_mm, 2.0)
    kk, jj, ii = np.meshgrid(*(np.arange(s) for s in out.shape), indexing="ij")
    idx = np.stack([ii, jj, kk, np.ones_like(ii)], axis=-1).astype(float)
    world = (idx @ out.index_to_world.T)[..., :3]
    inner = (slice(3, -3),) * 3
    np.testing.assert_allclose(out.data[inner], world_value(world)[inner], atol=1e-3)


def test_cache_reuses_and_widens() -> None:
    prepare.clear_cache()
    vol = _volume((3.0, 3.0, 3.0), extent_mm=240.0, couch=False)
    g = _view()
    first = prepare_volume(vol, g, reach=Reach(10.0, 5.0))
    assert prepare_volume(vol, g, reach=Reach(8.0, 4.0)) is first  # covered: reused
    assert prepare_volume(vol, g.resized(32, 32), reach=Reach(8.0, 4.0)) is first  # same field
    wider = prepare_volume(vol, g, reach=Reach(30.0, 10.0))
    assert wider is not first and wider.reach.covers(Reach(30.0, 10.0))
    other = replace(vol)  # an equal but distinct volume object is prepared anew
    assert prepare_volume(other, g, reach=Reach(8.0, 4.0)) is not first
    prepare.clear_cache()


def test_reach_of_a_search() -> None:
    r = Reach.of_search(30.0, 15.0, translations=2)
    assert r.translation_mm == pytest.approx(30.0 * np.sqrt(2))
    assert 25.9 < r.rotation_deg < 28.0  # three 15-degree angles compose to at most ~26 degrees
    m = offsets_to_matrix([0.0, 0.0, 10.0, 0.0, 0.0, 0.0], _view())
    assert Reach.of_search(5.0, 1.0, initial_motion=m, isocenter_mm=ISO).translation_mm > 10.0
    with pytest.raises(ValueError, match="rotation"):
        Reach(1.0, 200.0)


def test_bad_input() -> None:
    vol = _volume((3.0, 3.0, 3.0), extent_mm=120.0, couch=False)
    with pytest.raises(ValueError, match="geometries"):
        prepare_volume(vol, [])
    with pytest.raises(ValueError, match="Volume"):
        prepare_volume(np.zeros((4, 4, 4)), _view())  # type: ignore[arg-type]
    renderer = prepare_volume(vol, _view(), cache=False).renderer
    with pytest.raises(ValueError, match="not prepared"):
        renderer.render(_view(), level=0)
    with pytest.raises(ValueError, match="at least one volume"):
        DRRRenderer(vol, levels=[None])


def test_air_only_volume_keeps_the_whole_box() -> None:
    vol = Volume.from_grid(np.full((20, 20, 20), -1000.0, np.float32), 4.0, center_mm=ISO)
    prep = prepare_volume(vol, _view(), cache=False)
    assert np.all(prep.renderer.render(_view(), level=2) == 0.0)
    assert ndimage is not None


def _head_on_couch(with_couch: bool) -> Volume:
    """The blob (a head) on a couch plate 40 mm behind it, joined to it by thin posts (a head
    rest's legs, 6 mm across), on a 3 mm grid; without the couch: the head alone."""
    sp, n = 3.0, 110
    axes = [ISO[a] + (np.arange(n) - (n - 1) / 2.0) * sp for a in range(3)]
    z, y, x = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    hu = _blob_hu(np.stack([x, y, z], axis=-1))
    if with_couch:
        dy = y - ISO[1]
        hu[(dy > 125.0) & (dy < 135.0) & (np.abs(x - ISO[0]) < 150.0)] = 200.0  # the plate
        for px in (-30.0, 30.0):
            for pz in (-30.0, 30.0):
                post = (np.abs(x - ISO[0] - px) < 3.0) & (np.abs(z - ISO[2] - pz) < 3.0) & (dy > 60.0) & (dy < 130.0)
                hu[post] = 200.0
    return Volume.from_grid(hu, sp, center_mm=ISO)


def test_the_couch_and_the_air_around_the_body_are_not_rendered() -> None:
    """A CT's couch, joined to the head by a head rest's thin legs, is cut off at the legs and
    set to air, as is the air around the body: the DRRs are those of the head alone (but for
    the legs' stubs within BODY_KEEP_MM of it), and they cross only the body's box."""
    g = _view(0.0, 0.0, fmt_cm=27.0)  # frontal: every ray crosses the couch behind the head
    reach = Reach(10.0, 4.0)
    couch = prepare_volume(_head_on_couch(True), g, reach=reach, cache=False)
    head = prepare_volume(_head_on_couch(False), g, reach=reach, cache=False, body=False)
    kept = prepare_volume(_head_on_couch(True), g, reach=reach, cache=False, body=False)
    assert couch.body and not kept.body
    level = couch.levels[2]
    plate = np.array([ISO[0] + 100.0, ISO[1] + 130.0, ISO[2]])  # in the plate, far from the head
    assert float(level.sample(plate)) == -1000.0  # air (or outside the box, also air)
    # the box ends behind the head (its 85 mm, the keep margin and the crop's margin), not at the plate
    far_y = (level.index_to_world @ np.array([0, level.shape[1] - 1, 0, 1.0]))[1] - ISO[1]
    assert far_y < 85.0 + prepare.BODY_KEEP_MM + 2 * 2 * couch.spacing_mm[2] + 4.0
    motion = offsets_to_matrix([3.0, -2.0, 0.0, 2.0, -1.0, 3.0], g)
    mask = g.field_mask()
    a, b, c = (p.renderer.render(g, motion, level=2)[mask] for p in (couch, head, kept))
    # the couch plate adds 10 mm of 200 HU (~0.25) to every ray behind the head
    assert np.median(c - b) > 0.2
    # without it: the head's DRR, but for the legs' stubs (4 posts of 6 mm, at most 12 mm long)
    assert np.median(np.abs(a - b)) < 0.01 * np.ptp(b)
    assert np.abs(a - b).max() < 0.1 * np.ptp(b)


def test_a_finer_scanner_grid_gets_the_same_levels_and_rays() -> None:
    """The same anatomy on a 1 x 1 x 3 mm and a 0.5 x 0.5 x 2.5 mm grid: level 0 is never finer
    than MIN_LEVEL0_MM, so both get the same level grids and the registration's images the same
    pixels (on the shared real CT resampled so: 0.87-1.14x the time, where it was 3-4x)."""
    from registration.core.images import XRayImage
    from registration.core.prepare.params import MIN_LEVEL0_MM
    from registration.core.problem import LevelProblem

    g = _view(20.0, -10.0, fmt_cm=27.0, pixels=384)
    a = prepare_volume(_volume((1.0, 1.0, 3.0), extent_mm=240.0), g, cache=False)
    b = prepare_volume(_volume((0.5, 0.5, 2.5), extent_mm=240.0), g, cache=False)
    assert a.spacing_mm == pytest.approx(b.spacing_mm)
    # the field's own level 1 (1.42 mm for a 27 cm format) is finer than twice the floor
    assert a.spacing_mm[1] == pytest.approx(2 * MIN_LEVEL0_MM)
    image = a.renderer.render(g, level=1)
    view = XRayImage(image, np.ones(image.shape, dtype=bool), g, kind="drr")
    for image_px, level in ((64, 2), (128, 1)):  # the capture's and the polish's
        sizes = [LevelProblem.prepare(p.renderer, (view,), image_px=image_px, volume_level=level, motion=np.eye(4),
                                      margin_mm=None).views[0].geometry.rows for p in (a, b)]  # fmt: skip
        assert sizes[0] == sizes[1]


def test_the_probes_level_0_is_the_crop_with_its_body_mask() -> None:
    """The confidence's level 0 of a CT on a grid coarser than the floor (the crop and the
    body's mask written in one pass) is exactly the crop of the volume with
    ``mask_outside_body`` applied: the couch set to air, the head kept."""
    from registration.core.prepare import mask_outside_body, probe_blocks
    from registration.core.prepare.body import body_region

    rng = np.random.default_rng(3)
    data = np.full((40, 60, 60), -1000.0, dtype=np.float32)
    data[8:32, 15:45, 15:45] = rng.normal(40.0, 200.0, (24, 30, 30)).astype(np.float32)  # the head
    data[:, 52:56, 5:55] = 300.0  # a couch plate under it, joined to nothing
    vol = Volume.from_grid(data, (2.0, 2.0, 3.0))
    blocks = probe_blocks(vol)
    assert blocks.body is not None
    lo, hi = np.array([3, 4, 2]), np.array([57, 58, 37])  # (i, j, k)
    crop = Volume(data[2:38, 4:59, 3:58], vol.index_to_world @ _shifted(lo))
    expected = mask_outside_body(crop, vol, blocks)
    got = body_region(vol, lo, hi, blocks)
    np.testing.assert_array_equal(got.index_to_world, expected.index_to_world)
    np.testing.assert_array_equal(got.data, expected.data)
    assert (got.data[:, 48:, :] == -1000.0).all()  # the couch is gone
    assert (got.data[6:30, 11:41, 12:42] == crop.data[6:30, 11:41, 12:42]).mean() > 0.99  # the head is not


def _shifted(lo: np.ndarray) -> np.ndarray:
    """The index affine that starts at index ``lo`` ((i, j, k))."""
    t = np.eye(4)
    t[:3, 3] = lo
    return t


def test_the_probes_level_0_is_not_finer_than_the_floor() -> None:
    """The confidence's level 0 of a 0.5 x 0.5 x 2.5 mm grid: 1 x 1 x 2.5 mm block averages, each
    placed at its block's centre (a ramp along x keeps its values where they were)."""
    from registration.core.preparation import _floor_factors

    x = np.arange(9) * 0.5 + 3.0  # the ramp's value is the world x
    data = np.broadcast_to(x, (4, 6, 9)).astype(np.float32).copy()
    vol = Volume.from_grid(data, (0.5, 0.5, 2.5), center_mm=(5.0, 0.0, 0.0))
    assert _floor_factors(vol, 1.0) == (2, 2, 1)
    coarse = vol.downsample(_floor_factors(vol, 1.0))
    np.testing.assert_allclose(coarse.spacing_mm, (1.0, 1.0, 2.5))
    assert coarse.shape == (4, 3, 4)
    world_x = (coarse.index_to_world @ np.stack([np.arange(4), np.zeros(4), np.zeros(4), np.ones(4)]))[0]
    world_x_src = (vol.index_to_world @ np.stack([np.arange(9), np.zeros(9), np.zeros(9), np.ones(9)]))[0]
    # each block's value (the mean of its two source voxels) sits at their mean position
    np.testing.assert_allclose(coarse.data[0, 0], (data[0, 0, 0:8:2] + data[0, 0, 1:8:2]) / 2)
    np.testing.assert_allclose(world_x, (world_x_src[0:8:2] + world_x_src[1:8:2]) / 2)
    assert _floor_factors(coarse, 1.0) == (1, 1, 1)


def test_an_isotropic_3dra_finer_than_the_floor_keeps_its_own_pyramid() -> None:
    """A 3DRA of 0.71 mm voxels (the phantom's 256^3 of an 18 cm field) is not held to the CT's
    1 mm floor: its levels are its own block averages, 1.42 and 2.85 mm."""
    g = _view(fmt_cm=27.0, pixels=384)
    vol = _volume((0.712, 0.712, 0.712), extent_mm=180.0, couch=False)
    prep = prepare_volume(vol, g, cache=False)
    assert prep.spacing_mm[1] == pytest.approx(2 * 0.712) and prep.spacing_mm[2] == pytest.approx(4 * 0.712)


@pytest.mark.parametrize("polish", [{"enabled": False}, {"volume_level": 2}], ids=["polish off", "polish at level 2"])
def test_one_view_gets_the_depth_probes_level_whatever_its_polish(polish: dict) -> None:
    """The confidence's depth probe renders one view's estimate at level 1: a CT's levels are
    built in mm, not a pyramid, so that level is prepared even when the polish is off or renders
    coarser (the assessment found no level to render before)."""
    from registration.core.depth import DEPTH_VOLUME_LEVEL, depth_probe
    from registration.core.images import XRayImage
    from registration.core.register import PolishOptions, RegistrationOptions, prepared_volume

    g = _view(20.0, -10.0, fmt_cm=27.0, pixels=128)
    vol = _volume((1.0, 1.0, 3.0), extent_mm=240.0)
    image = DRRRenderer(vol, levels=1).render(g)
    view = XRayImage(image, np.ones(image.shape, dtype=bool), g, kind="drr")
    options = RegistrationOptions(polish=PolishOptions(**polish))
    assert DEPTH_VOLUME_LEVEL not in options.volume_levels()  # what the search itself renders
    prepared = prepared_volume(vol, (view,), np.eye(4), options)
    assert prepared.renderer.has_level(DEPTH_VOLUME_LEVEL)
    probe = depth_probe(prepared.renderer, view, np.eye(4))
    # the image is the volume's own DRR at the true pose: the probe stays within a fraction of
    # level 1's 2 mm voxel of it, along the beam and across
    assert abs(probe.tz_mm) < 1.0 and probe.shift_mm < 0.5, probe.to_dict()
