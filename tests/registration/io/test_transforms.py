"""Registration results in other tools' frames (registration.io.transforms).

Truth comes from outside the converters: SimpleITK resampling a volume with the written file
must move a blob where the patient motion moves anatomy (CONVENTIONS §4), and the engine's own
projection (``CArm.project``) must put every point where the other tool's camera model does.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk
from scipy.spatial.transform import Rotation

from registration.core.geometry import CArm
from registration.core.volume import Volume
from registration.io.transforms import (
    ITK_COMMENT,
    RAS_FROM_LPS,
    diffdrr_rays,
    from_deepdrr,
    from_diffdrr,
    from_pinhole,
    read_itk_transform,
    to_deepdrr,
    to_diffdrr,
    to_pinhole,
    write_itk_transform,
)


def _motion(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    m = np.eye(4)
    m[:3, :3] = Rotation.from_rotvec(rng.normal(size=3) * 0.1).as_matrix()  # ~6 degrees
    m[:3, 3] = rng.uniform(-8, 8, size=3)
    return m


def _blob_volume() -> tuple[Volume, np.ndarray]:
    """A Gaussian blob (sigma 3 mm) on a 1.5 mm grid, tilted and offset; its centre in LPS."""
    n = 40
    affine = np.eye(4)
    affine[:3, :3] = Rotation.from_euler("z", 10, degrees=True).as_matrix() * 1.5
    affine[:3, 3] = (-30.0, -25.0, -28.0)
    center_index = np.array([17.0, 21.0, 19.0])  # (i, j, k)
    k, j, i = np.mgrid[0:n, 0:n, 0:n].astype(np.float64)
    d2 = ((np.stack([i, j, k], -1) - center_index) * 1.5) ** 2
    data = 1000.0 * np.exp(-d2.sum(-1) / (2 * 3.0**2))
    return Volume(data.astype(np.float32), affine), (affine @ np.append(center_index, 1.0))[:3]


def _to_sitk(volume: Volume) -> sitk.Image:
    image = sitk.GetImageFromArray(volume.data)
    spacing = volume.spacing_mm
    image.SetSpacing(spacing.tolist())
    image.SetDirection((volume.index_to_world[:3, :3] / spacing).reshape(-1).tolist())
    image.SetOrigin(volume.index_to_world[:3, 3].tolist())
    return image


@pytest.mark.parametrize("suffix", [".tfm", ".h5"])
def test_itk_transform_resamples_the_volume_as_the_patient_moved(tmp_path: Path, suffix: str) -> None:
    motion = _motion(0)
    path = write_itk_transform(motion, tmp_path / f"result{suffix}")
    np.testing.assert_allclose(read_itk_transform(path), motion, atol=1e-12)
    if suffix == ".tfm":
        assert ITK_COMMENT in path.read_text() and "inverse of the patient motion" in path.read_text()
    volume, blob = _blob_volume()
    image = _to_sitk(volume)
    moved = sitk.Resample(image, image, sitk.ReadTransform(str(path)), sitk.sitkLinear, 0.0)
    data = sitk.GetArrayFromImage(moved).astype(np.float64)  # (k, j, i)
    k, j, i = np.mgrid[0 : data.shape[0], 0 : data.shape[1], 0 : data.shape[2]]
    index = np.stack([i, j, k, np.ones_like(i)], -1).reshape(-1, 4).astype(np.float64)
    world = (index @ volume.index_to_world.T)[:, :3]
    weights = data.reshape(-1)
    centroid = (world * weights[:, None]).sum(0) / weights.sum()
    # the blob (anatomy at X) must appear at M @ X; linear interpolation of a sigma-3 mm blob on a
    # 1.5 mm grid keeps its centroid to a few hundredths of a mm, a wrong direction would miss by ~2x8 mm
    np.testing.assert_allclose(centroid, (motion @ np.append(blob, 1.0))[:3], atol=0.05)


def test_itk_transform_refuses_non_rigid_input(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="not a rigid transform"):
        write_itk_transform(np.diag([2.0, 1.0, 1.0, 1.0]), tmp_path / "x.tfm")
    with pytest.raises(ValueError, match="ITK transform file ends with"):
        write_itk_transform(np.eye(4), tmp_path / "x.json")
    (tmp_path / "bad.tfm").write_text("not a transform\n")
    with pytest.raises(ValueError, match="not a readable ITK transform"):
        read_itk_transform(tmp_path / "bad.tfm")


CARMS = [
    CArm(primary_deg=0.0, secondary_deg=0.0, rows=48, cols=64, pixel_mm=(0.8, 0.6)),
    CArm(primary_deg=35.0, secondary_deg=-20.0, rows=64, cols=64, isocenter_mm=(5.0, -10.0, 20.0)),
    CArm(primary_deg=-90.0, secondary_deg=10.0, sid_mm=1100.0, sod_mm=700.0, rows=32, cols=40),
]


def _points(seed: int, n: int = 20) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-60, 60, size=(n, 3))


@pytest.mark.parametrize("carm", CARMS, ids=["frontal", "oblique", "lateral"])
def test_diffdrr_camera_sees_every_point_where_the_engine_projects_it(carm: CArm) -> None:
    volume, _ = _blob_volume()
    motion = _motion(1)
    pose = to_diffdrr(motion, carm, volume)
    source, pixels = diffdrr_rays(pose)
    # DiffDRR's world is RAS about the volume centre; back to LPS, then into the moved patient
    lps_from_diffdrr = np.linalg.inv(RAS_FROM_LPS)
    lps_from_diffdrr[:3, 3] = volume.center_mm
    to_engine = motion @ lps_from_diffdrr
    engine_source = (to_engine @ np.append(source, 1.0))[:3]
    np.testing.assert_allclose(engine_source, carm.source_mm, atol=1e-9)
    for r, c in [(0, 0), (carm.rows - 1, 0), (3, carm.cols - 2), (carm.rows // 2, carm.cols // 2)]:
        point = (to_engine @ np.append(pixels[r, c], 1.0))[:3]
        midway = 0.5 * (engine_source + point)  # any point of the ray projects to the same pixel
        np.testing.assert_allclose(carm.project(midway[None])[0], [c, r], atol=1e-6)
    np.testing.assert_allclose(from_diffdrr(pose.extrinsic, carm, volume), motion, atol=1e-12)
    assert (pose.height, pose.width, pose.sdd) == (carm.rows, carm.cols, carm.sid_mm)


@pytest.mark.parametrize("carm", CARMS, ids=["frontal", "oblique", "lateral"])
@pytest.mark.parametrize("frame", ["LPS", "RAS"])
def test_pinhole_projection_equals_the_engines(carm: CArm, frame: str) -> None:
    motion = _motion(2)
    k, extrinsic = to_pinhole(motion, carm, frame=frame)
    points = _points(3)
    homogeneous = np.c_[points, np.ones(len(points))]
    world = homogeneous @ (RAS_FROM_LPS.T if frame == "RAS" else np.eye(4))
    p = (k @ (world @ extrinsic.T)[:, :3].T).T
    # anatomy at X in the volume is imaged at M @ X (CONVENTIONS §4)
    np.testing.assert_allclose(p[:, :2] / p[:, 2:], carm.project((homogeneous @ motion.T)[:, :3]), atol=1e-7)
    np.testing.assert_allclose(from_pinhole(extrinsic, carm, frame=frame), motion, atol=1e-12)
    k2, extrinsic2 = to_deepdrr(motion, carm, frame=frame)  # DeepDRR's CameraProjection is this pinhole
    np.testing.assert_array_equal(k2, k)
    np.testing.assert_allclose(from_deepdrr(extrinsic2, carm, frame=frame), motion, atol=1e-12)


def test_shifted_detectors_are_refused() -> None:
    carm = CArm(detector_shift_mm=(1.0, 0.0, 0.0))
    with pytest.raises(ValueError, match="nominal C-arm"):
        to_pinhole(np.eye(4), carm)
