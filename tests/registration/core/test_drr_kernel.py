"""The fast Joseph kernel against a plain float64 statement of the same sum.

``test_drr.py`` holds the renderer to the true line integrals and to ``render_reference`` at
quadrature tolerance (~0.5 %); this file holds the compiled kernel (fixed-point marching,
float32 samples, empty-space leaping, serial and parallel) to its own definition, written here
without any of those devices, at float32 rounding tolerance. A change to the kernel that alters
what it computes (a slice dropped, an end weight, a sample off by a fraction of a voxel) fails
here even when it stays within the quadrature tolerance of the other tests.
"""

import numpy as np
import pytest
from scipy import ndimage

from registration.core import drr, drr_kernels
from registration.core.drr import DRRRenderer
from registration.core.drr_kernels import _BLOCK
from registration.core.geometry import CArm, offsets_to_matrix
from registration.core.volume import Volume, hu_to_mu_per_mm


def _joseph_definition(volume: Volume, geometry: CArm, motion: np.ndarray | None) -> np.ndarray:
    """Joseph's sum of the DRR, float64, ray by ray, from the renderer's docstring:

    each pixel's ray (source to pixel center, volume moved by ``motion``) in voxel indices is
    clipped to the box of voxels that can contribute (attenuation > 0, padded by one voxel);
    along its dominant index axis m the bilinear samples at the integer slices inside the clipped
    span [e0, e1], plus one beyond each end, are integrated as the function linear between
    slices (trapezoid inside, exact areas over the partial end slices), times mm per slice.
    """
    mu = hu_to_mu_per_mm(volume.data).astype(np.float64)  # (nk, nj, ni)
    nk, nj, ni = mu.shape
    n_ijk = np.array([ni, nj, nk])
    pad = 3
    padded = np.pad(mu, pad)
    positive = np.argwhere(mu > 0)[:, ::-1]  # (i, j, k)
    lo = np.maximum(positive.min(axis=0) - 1, 0).astype(float)
    hi = np.minimum(positive.max(axis=0) + 1, n_ijk - 1).astype(float)
    m_vol = np.eye(4) if motion is None else np.asarray(motion, dtype=float)
    to_index = volume.index_from_world @ np.linalg.inv(m_vol)
    source = (to_index @ np.append(geometry.source_mm, 1.0))[:3]
    i2w = volume.index_to_world[:3, :3]
    out = np.zeros((geometry.rows, geometry.cols))
    for r in range(geometry.rows):
        for c in range(geometry.cols):
            target = (to_index @ np.append(geometry.pixel_to_world(c, r), 1.0))[:3]
            d = target - source
            tmin, tmax = 0.0, np.inf
            for a in range(3):  # slab clip, t >= 0
                if d[a] == 0.0:
                    if not lo[a] <= source[a] <= hi[a]:
                        tmax = -1.0
                    continue
                t0, t1 = sorted(((lo[a] - source[a]) / d[a], (hi[a] - source[a]) / d[a]))
                tmin, tmax = max(tmin, t0), min(tmax, t1)
            if not tmin < tmax:
                continue
            m = int(np.argmax(np.abs(d)))  # ties: the first axis, as the kernel
            p, q = [a for a in range(3) if a != m]
            e0, e1 = sorted((source[m] + tmin * d[m], source[m] + tmax * d[m]))
            e0, e1 = max(e0, 0.0), min(e1, n_ijk[m] - 1.0)
            if not e0 < e1:
                continue
            first, last = int(np.ceil(e0)), int(np.floor(e1))
            slices = np.arange(first - 1, max(last, first) + 2)  # one beyond each end
            point = source[:, None] + (slices - source[m]) / d[m] * d[:, None]  # (3, n) as (i, j, k)
            point[m] = slices  # exactly on the slices
            v = ndimage.map_coordinates(padded, point[::-1] + pad, order=1, mode="nearest")
            if e1 < first:  # within one slice interval
                f = 0.5 * (e0 + e1) - (first - 1)
                total = (e1 - e0) * (v[0] + f * (v[1] - v[0]))
            else:
                inner = v[1:-1]  # slices first .. last
                f0, f1 = first - e0, e1 - last
                v_e0 = inner[0] + f0 * (v[0] - inner[0])
                v_e1 = inner[-1] + f1 * (v[-1] - inner[-1])
                total = inner.sum() - 0.5 * (inner[0] + inner[-1])
                total += 0.5 * (f0 * (v_e0 + inner[0]) + f1 * (v_e1 + inner[-1]))
            out[r, c] = total * np.linalg.norm(i2w @ d) / abs(d[m])
    return out


@pytest.fixture(scope="module")
def islands():
    """Smooth tissue in two islands in exact air, on an anisotropic grid with an oblique
    affine: rays leap over the air, all three dominant axes occur, no axis is special."""
    rng = np.random.default_rng(11)
    data = ndimage.gaussian_filter(rng.normal(0.0, 1.0, (30, 36, 42)), 1.5)
    data = data / np.abs(data).max() * 800.0 + 200.0
    k, j, i = np.indices(data.shape)
    first = (i - 13) ** 2 + (j - 15) ** 2 + (k - 14) ** 2 < 10**2
    near = first | ((i - 30) ** 2 + (j - 22) ** 2 + (k - 15) ** 2 < 8**2)
    data[~near] = -1000.0
    spacing = np.diag([2.2, 2.6, 3.0])
    c, s = np.cos(0.3), np.sin(0.3)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    affine = np.eye(4)
    affine[:3, :3] = rot @ spacing
    affine[:3, 3] = -affine[:3, :3] @ (np.array([42, 36, 30]) - 1) / 2.0 + (3.0, -2.0, 1.0)
    return Volume(data.astype(np.float32), affine)


def _view(primary: float, secondary: float, **kw) -> CArm:
    return CArm(primary, secondary, rows=24, cols=28, pixel_mm=(4.0, 4.0), **kw)


VIEWS = {
    "frontal": _view(0.0, 0.0),
    "oblique": _view(35.0, 20.0),
    "lateral": _view(-90.0, -10.0),
    "steep-cranial": _view(10.0, 70.0),
    "shifted-tilted": _view(30.0, -25.0, detector_shift_mm=(2.0, 1.0, 0.0), detector_tilt_deg=(1.0, 0.0, 0.5)),
}


@pytest.mark.parametrize("name", list(VIEWS))
def test_kernel_equals_its_definition(islands, name, monkeypatch):
    geometry = VIEWS[name]
    motion = offsets_to_matrix((4.0, -3.0, 6.0, 5.0, -4.0, 7.0), geometry)
    expected = _joseph_definition(islands, geometry, motion)
    scale = float(expected.max())
    assert scale > 1.0  # the islands are in the field
    assert (expected == 0).mean() > 0.05  # and some rays miss them
    renderer = DRRRenderer(islands, levels=1)
    for serial in (True, False):
        monkeypatch.setattr(drr, "_SERIAL_SAMPLES", 10**12 if serial else 0)
        fast = renderer.render(geometry, motion)
        # float32 samples and sums against float64: ~1e-7 of the largest line integral, measured
        # <= 3e-7 here; 1e-5 is still far below what a changed sum would show (one voxel's
        # share of a ray, ~1e-2).
        np.testing.assert_allclose(fast, expected, rtol=0, atol=1e-5 * scale)
        assert np.array_equal(fast == 0, expected == 0)


@pytest.mark.parametrize("dtype", [np.float32, np.int16, np.float64])
def test_level_arrays_equal_their_definition(dtype):
    """A level's padded attenuation, its transposed copy, its clip box and its empty-space
    distances, written in one compiled pass, are exactly what ``hu_to_mu_per_mm``, ``np.pad``,
    a transposed copy and a block-wise any() of the padded array give (bit for bit: the
    kernels' sums depend on nothing else)."""
    rng = np.random.default_rng(7)
    hu = np.full((23, 31, 44), -1000.0)
    hu[5:12, 8:20, 10:30] = rng.normal(-300.0, 600.0, (7, 12, 20))  # some voxels at or below air
    hu[18, 27, 40] = 200.0  # an island far from the rest: empty space between them
    hu = hu.astype(dtype)
    level = drr._Level(Volume(hu, np.diag([0.7, 0.7, 2.0, 1.0])))
    mu = hu_to_mu_per_mm(hu.astype(np.float32))
    padded = np.pad(mu, drr._PAD)
    assert np.array_equal(level.mu, padded.reshape(-1))
    assert np.array_equal(level.mu_t, np.ascontiguousarray(padded.transpose(0, 2, 1)).reshape(-1))
    positive = np.argwhere(mu > 0)  # (k, j, i)
    assert np.array_equal(level.lo, np.maximum(positive.min(axis=0) - 1, 0)[::-1])
    assert np.array_equal(level.hi, np.minimum(positive.max(axis=0) + 1, np.array(mu.shape) - 1)[::-1])
    b = _BLOCK
    grid = np.zeros(tuple(-(-n // b) * b for n in padded.shape), dtype=bool)
    grid[: padded.shape[0], : padded.shape[1], : padded.shape[2]] = padded > 0
    blocks = grid.reshape(grid.shape[0] // b, b, grid.shape[1] // b, b, grid.shape[2] // b, b).any(axis=(1, 3, 5))
    distance = ndimage.distance_transform_cdt(~blocks, metric="chessboard")
    assert level.use_empty
    assert np.array_equal(level.empty, np.minimum(distance, 255).astype(np.uint8).reshape(-1))


def test_leaps_are_looked_up_only_where_a_ray_can_leap(islands, monkeypatch):
    """A volume whose air lies within two blocks of attenuation everywhere (no ray can leap)
    renders without the leaps' look-ups, to the values the look-ups give bit for bit; two
    islands in air keep them."""
    centre = np.eye(4)
    centre[:3, 3] = -9.5  # the 20 mm cube about the iso-center
    hu = np.full((20, 20, 20), 300.0, dtype=np.float32)
    hu[8:14, 4:16, 4:16] = -1000.0  # a slab of air inside, three blocks thick: two from attenuation at most
    volume = Volume(hu, centre)
    renderer = DRRRenderer(volume, levels=1)
    assert not renderer._level(0).use_empty
    names = ("frontal", "lateral", "steep-cranial")
    images = {name: renderer.render(VIEWS[name]) for name in names}  # the kernels compiled as shipped
    # a level built while the distances are kept down to 2 blocks: its rays look the leaps up
    monkeypatch.setattr(drr_kernels, "_LEAP_MIN", 2)
    looking = DRRRenderer(volume, levels=1)
    monkeypatch.undo()
    assert looking._level(0).use_empty
    for name in names:
        assert (images[name] > 0).sum() > 20, name  # the cube covers some 5 x 5 pixels at least
        np.testing.assert_array_equal(looking.render(VIEWS[name]), images[name])
    assert DRRRenderer(islands, levels=1)._level(0).use_empty


def test_a_lazy_level_writes_only_what_its_rays_read(islands):
    """A level built lazily renders every view exactly as the eagerly built one, and writes the
    transposed copy only for a view with rays dominated by the i axis (a lateral view) and the
    (k, j, i) array only for one with rays dominated by j or k (a frontal view)."""
    eager = DRRRenderer(islands, levels=1)
    motion = offsets_to_matrix([1.5, -2.0, 3.0, 4.0, -3.0, 2.0], VIEWS["oblique"])
    # at LAO 60 (this volume's affine turns it 17 deg) the rays straddle the i / j diagonal
    views = {**VIEWS, "diagonal": _view(60.0, 0.0)}
    for name, reads, reads_t in (("frontal", True, False), ("lateral", False, True), ("diagonal", True, True)):
        lazy = eager.with_levels({0: islands}, lazy=True)
        level = lazy._level(0)
        assert not level.has_mu and not level.has_mu_t
        for parallel in (False, True):
            got = lazy.render(views[name], motion, parallel=parallel)
            np.testing.assert_array_equal(got, eager.render(views[name], motion, parallel=parallel))
        assert (level.has_mu, level.has_mu_t) == (reads, reads_t), name
        # what the first render wrote, the rest of the level holds as the eager one does
        whole = eager._level(0)
        np.testing.assert_array_equal(level.lo, whole.lo)
        np.testing.assert_array_equal(level.empty, whole.empty)
        if reads:
            np.testing.assert_array_equal(level.mu, whole.mu)
        if reads_t:
            np.testing.assert_array_equal(level.mu_t, whole.mu_t)
    # one lazy level asked for the frontal view, then the lateral: the second array joins the first
    lazy = eager.with_levels({0: islands}, lazy=True)
    for name in ("frontal", "lateral", "frontal"):
        np.testing.assert_array_equal(lazy.render(VIEWS[name], motion), eager.render(VIEWS[name], motion))
    assert lazy._level(0).complete
    # ready(): what a render of a view would read, written before it (the probes' level 0)
    lazy = eager.with_levels({0: islands}, lazy=True)
    lazy.ready(VIEWS["lateral"], motion, level=0)
    assert (lazy._level(0).has_mu, lazy._level(0).has_mu_t) == (False, True)
    np.testing.assert_array_equal(lazy.render(VIEWS["lateral"], motion), eager.render(VIEWS["lateral"], motion))
