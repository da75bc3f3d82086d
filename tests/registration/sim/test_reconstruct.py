"""FDK reconstruction of analytic spheres from a simulated (bent, calibrated) rotational run."""

from __future__ import annotations

import math

import numpy as np
import pytest

from registration.core.geometry import CArm
from registration.core.volume import MU_WATER_PER_MM, format_grid
from registration.sim.calibration import SpherePhantom, machine_based_error_mm, simulate_sphere_image
from registration.sim.reconstruct import fdk, parker_weights, ramp_kernel_spectrum, reconstruct_run
from registration.sim.rotational_run import RotationalRun, rotational_run, run_angles

#: Small sizes so the file runs in well under a minute on 2 shared cores.
FORMAT_CM = 15.0  # FOV 101 mm at the iso-center
VOXELS = 64  # 1.58 mm voxels
PIXELS = 128  # 0.79 mm at the iso-center
PROJECTIONS = 60

BEADS_MM = np.array([[20.0, 0.0, 0.0], [0.0, -18.0, 12.0], [-12.0, 15.0, -20.0], [5.0, 22.0, -8.0]])
WATER_RADIUS_MM = 38.0
BEAD_RADIUS_MM = 4.0


def _phantom() -> SpherePhantom:
    """A water sphere (0 HU) holding four beads of 1000 HU (mu = 2 mu_water)."""
    centers = np.vstack([np.zeros((1, 3)), BEADS_MM])
    radii = [WATER_RADIUS_MM] + [BEAD_RADIUS_MM] * len(BEADS_MM)
    return SpherePhantom(centers, radii, [MU_WATER_PER_MM] * (1 + len(BEADS_MM)))


def _imager(phantom: object, geometry: CArm, index: int):
    assert isinstance(phantom, SpherePhantom)
    return simulate_sphere_image(phantom, geometry, supersample=2, full_frame=True), geometry.field_mask()


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    mp = pytest.MonkeyPatch()
    mp.setenv("ROADMAP3D_CACHE", str(tmp_path_factory.mktemp("cache")))
    phantom = _phantom()
    kw = dict(image_format_cm=FORMAT_CM, projections=PROJECTIONS, pixels=PIXELS, imager=_imager)
    calibrated = rotational_run(phantom, **kw)
    uncalibrated = rotational_run(phantom, calibrate=False, **kw)
    yield phantom, calibrated, uncalibrated
    mp.undo()


@pytest.fixture(scope="module")
def volumes(runs):
    _, calibrated, uncalibrated = runs
    return (
        reconstruct_run(calibrated, volume_format_cm=FORMAT_CM, voxels=VOXELS),
        reconstruct_run(uncalibrated, volume_format_cm=FORMAT_CM, voxels=VOXELS),
    )


def _world_grid(volume):
    nk, nj, ni = volume.shape
    idx = np.stack(np.meshgrid(np.arange(ni), np.arange(nj), np.arange(nk), indexing="ij"), -1)
    idx = np.transpose(idx, (2, 1, 0, 3)).astype(np.float64)  # (k, j, i, [i, j, k])
    return idx @ volume.index_to_world[:3, :3].T + volume.index_to_world[:3, 3]


def _bead_offsets_vox(volume) -> np.ndarray:
    """Signal-weighted centroid of each bead (HU above the water) minus its true center, voxels."""
    out = []
    w2i = volume.index_from_world
    for bead in BEADS_MM:
        idx = w2i[:3, :3] @ bead + w2i[:3, 3]
        i, j, k = np.round(idx).astype(int)
        win = np.clip(volume.data[k - 4 : k + 5, j - 4 : j + 5, i - 4 : i + 5].astype(np.float64), 0.0, None)
        kk, jj, ii = np.mgrid[k - 4 : k + 5, j - 4 : j + 5, i - 4 : i + 5]
        center = np.array([(win * ii).sum(), (win * jj).sum(), (win * kk).sum()]) / win.sum()
        out.append(center - idx)
    return np.array(out)


# ----- pieces ----------------------------------------------------------------------------
def test_ramp_spectrum_is_a_windowed_ramp():
    spec = ramp_kernel_spectrum(256, window="ram-lak")
    f = np.arange(spec.size) / 256.0
    assert abs(spec[0]) < 1e-3  # the band-limited kernel's DC is ~0 (1/(4 N) from truncation)
    assert np.allclose(spec[10:100], f[10:100], rtol=0.02)  # |f| in cycles per pixel
    hann = ramp_kernel_spectrum(256)
    assert hann[-1] == pytest.approx(0.0, abs=1e-12) and hann[1] == pytest.approx(spec[1], rel=1e-3)
    with pytest.raises(ValueError, match="window"):
        ramp_kernel_spectrum(8, window="shepp")


def test_parker_weights_of_conjugate_rays_sum_to_one():
    rng = np.random.default_rng(0)
    half_fan = math.radians(10.0)
    for _ in range(200):
        gamma = rng.uniform(-half_fan * 0.99, half_fan * 0.99)
        beta = rng.uniform(0.0, math.pi + 2 * half_fan)
        conj = beta + math.pi + 2 * gamma
        if conj > math.pi + 2 * half_fan:
            conj = beta - math.pi + 2 * gamma
            if conj < 0:
                assert parker_weights(beta, np.array([gamma]), half_fan)[0] == pytest.approx(1.0)
                continue
        w = parker_weights(beta, np.array([gamma]), half_fan)[0]
        wc = parker_weights(conj, np.array([-gamma]), half_fan)[0]
        assert w + wc == pytest.approx(1.0, abs=1e-9)


def test_run_angles_and_bad_arcs():
    a = run_angles(120, 200.0)
    assert a.size == 120 and a[0] == -100.0 and a[-1] == 100.0
    with pytest.raises(ValueError, match="180"):
        run_angles(120, 170.0)
    with pytest.raises(ValueError, match="projections"):
        run_angles(1, 200.0)


def test_fdk_validates_inputs():
    geoms = [CArm.for_format(15.0, pixels=16, primary_deg=a) for a in (-100.0, 0.0, 100.0)]
    with pytest.raises(ValueError, match="one geometry per view"):
        fdk(np.zeros((2, 16, 16)), geoms, [-100, 0, 100], volume_format_cm=15.0, voxels=8)
    with pytest.raises(ValueError, match="180"):
        fdk(np.zeros((3, 16, 16)), geoms, [-80, 0, 80], volume_format_cm=15.0, voxels=8)
    with pytest.raises(ValueError, match="pixels"):
        fdk(np.zeros((3, 8, 8)), geoms, [-100, 0, 100], volume_format_cm=15.0, voxels=8)
    tilted = [g.with_angles(g.primary_deg, 10.0) for g in geoms]
    with pytest.raises(ValueError, match="propeller"):
        fdk(np.zeros((3, 16, 16)), tilted, [-100, 0, 100], volume_format_cm=15.0, voxels=8)


# ----- the run ---------------------------------------------------------------------------
def test_run_images_use_true_geometry_and_calibration_recovers_it(runs):
    _, run, uncal = runs
    assert isinstance(run, RotationalRun) and len(run) == PROJECTIONS
    assert run.images.shape == (PROJECTIONS, PIXELS, PIXELS)
    errors_true = [machine_based_error_mm(t, t.nominal()) for t in run.true_geometries]
    errors_cal = [
        machine_based_error_mm(t, c) for t, c in zip(run.true_geometries, run.calibrated_geometries, strict=True)
    ]
    assert min(errors_true) > 0.3  # the bending is real: the nominal geometry is off
    assert max(errors_cal) < 0.1  # the calibration run recovers it (paper: < 0.2 mm)
    assert all(c == c.nominal() for c in uncal.calibrated_geometries)
    # the images were formed with the true geometry: the iso-center bead-free water sphere's
    # projection is centered where the true geometry puts the iso-center
    img = run.images[PROJECTIONS // 2]
    rr, cc = np.mgrid[0:PIXELS, 0:PIXELS]
    centroid = np.array([(img * cc).sum(), (img * rr).sum()]) / img.sum()
    true_iso = run.true_geometries[PROJECTIONS // 2].project(np.zeros(3))
    assert np.linalg.norm(centroid - true_iso) < 1.0  # beads pull the centroid a little


# ----- the reconstruction ----------------------------------------------------------------
def test_grid_is_the_volume_format(volumes):
    vol, _ = volumes
    spacing, axis = format_grid(FORMAT_CM, voxels=VOXELS)
    assert vol.shape == (VOXELS,) * 3
    assert np.allclose(vol.spacing_mm, spacing)
    assert np.allclose(vol.center_mm, 0.0)
    assert np.allclose(vol.index_to_world[:3, 3], axis[0])
    assert "FDK" in vol.label


def test_uniform_sphere_and_air_in_hu(volumes):
    vol, _ = volumes
    world = _world_grid(vol)
    r = np.linalg.norm(world, axis=-1)
    near_bead = np.min([np.linalg.norm(world - b, axis=-1) for b in BEADS_MM], axis=0)
    water = vol.data[(r < WATER_RADIUS_MM - 8) & (near_bead > BEAD_RADIUS_MM + 5)]
    # noise-free projections: what is left is discretisation and the short-scan/cone-beam
    # approximation of FDK (cone half-angle ~4 deg here), a few HU
    assert abs(float(water.mean())) < 10.0
    assert float(water.std()) < 15.0
    air = vol.data[(r > WATER_RADIUS_MM + 6) & (vol.data > -1000.0)]
    assert air.size > 1000  # inside the reconstructable cylinder, outside the sphere
    assert abs(float(air.mean()) + 1000.0) < 40.0  # Hann-smoothed edge ringing of the sphere
    assert (vol.data == -1000.0).any()  # corners outside the field are set to air


def test_beads_at_the_right_position_and_hu(volumes):
    vol, _ = volumes
    offsets = _bead_offsets_vox(vol)
    assert np.abs(offsets).max() < 0.1  # issue: < 0.5 voxel; calibrated geometry gives ~0.02
    w2i = vol.index_from_world
    for bead in BEADS_MM:
        i, j, k = np.round(w2i[:3, :3] @ bead + w2i[:3, 3]).astype(int)
        peak = float(vol.data[k - 1 : k + 2, j - 1 : j + 2, i - 1 : i + 2].max())
        # 1000 HU bead of 5 voxels diameter: its core survives the Hann window within ~5 %
        assert peak == pytest.approx(1000.0, abs=50.0)


def test_calibration_matters(volumes):
    calibrated, nominal = volumes
    # reconstructing with the sensors' nominal geometry misplaces the beads by ~1 voxel
    # (the bending's few millimetres); the calibrated geometry puts them within 0.1 voxel
    assert np.linalg.norm(_bead_offsets_vox(nominal), axis=1).mean() > 0.5
    assert np.linalg.norm(_bead_offsets_vox(calibrated), axis=1).max() < 0.1


def test_reconstruct_3dra_is_cached(monkeypatch, tmp_path):
    pytest.importorskip("registration.sim.phantom")
    pytest.importorskip("registration.sim.xray")
    from registration.sim.reconstruct import reconstruct_3dra

    monkeypatch.setenv("ROADMAP3D_CACHE", str(tmp_path))
    kw = dict(volume_format_cm=22.0, contrast=True, voxels=24, pixels=48, projections=24)
    vol = reconstruct_3dra(0, **kw)
    assert vol.shape == (24, 24, 24) and "FDK" in vol.label
    assert list(tmp_path.glob("fdk-3dra-*.npz"))
    again = reconstruct_3dra(0, **kw)
    assert np.array_equal(again.data, vol.data)
