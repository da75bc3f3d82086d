"""NIfTI, NRRD and MetaImage volumes in the project's frame (CONVENTIONS §8).

The files are made by independent writers where one exists: nibabel for NIfTI (its RAS affine
and ``data[i, j, k]`` are what other tools write), NRRD headers written by hand. The truth is
where a voxel lies: the world point of voxel (i, j, k) by the file's own statement, turned to LPS
by negating x and y, must be the point ``index_to_world @ (i, j, k, 1)`` of the volume read, and
hold the same value.
"""

from __future__ import annotations

from pathlib import Path

import nibabel as nib
import numpy as np
import pytest

from registration.core.volume import Volume
from registration.io import dicom
from registration.io.volume_files import VolumeFileError, read_volume_file, write_volume_file

#: A sheared, scaled, offset RAS affine: every coefficient matters.
AFFINE_RAS = np.array([[0.9, 0.0, 0.1, -10.0], [0.0, 1.1, 0.0, 20.0], [0.05, 0.0, 3.0, 30.0], [0.0, 0.0, 0.0, 1.0]])
VOXELS_IJK = [(0, 0, 0), (3, 1, 2), (1, 4, 5), (3, 4, 5)]


def _data_ijk(seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(-1000, 2000, size=(4, 5, 6)).astype(np.int16)


def _check_voxels(volume: Volume, data_ijk: np.ndarray, affine_ras: np.ndarray, scale=(1.0, 0.0)) -> None:
    for ijk in VOXELS_IJK:
        ras = affine_ras @ np.array([*ijk, 1.0])
        lps = ras * np.array([-1, -1, 1, 1])
        # the same point, the same value (float64 arithmetic on the same numbers: exact to 1e-9 mm)
        np.testing.assert_allclose(volume.index_to_world @ np.array([*ijk, 1.0]), lps, atol=1e-9)
        i, j, k = ijk
        assert volume.data[k, j, i] == pytest.approx(data_ijk[i, j, k] * scale[0] + scale[1])


@pytest.mark.parametrize("suffix", [".nii", ".nii.gz"])
def test_nifti_sform_becomes_lps_and_kji(tmp_path: Path, suffix: str) -> None:
    data = _data_ijk()
    image = nib.Nifti1Image(data, AFFINE_RAS)
    image.set_sform(AFFINE_RAS, code=2)
    image.set_qform(np.diag([2.0, 2.0, 2.0, 1.0]), code=1)  # the sform wins when both are set
    image.header.set_slope_inter(0.5, -100.0)
    path = tmp_path / f"ct{suffix}"
    nib.save(image, path)
    volume = dicom.read_volume(path)  # every command reads volumes through this
    assert volume.shape == (6, 5, 4) and volume.meta["format"] == "NIfTI"
    assert "sform" in volume.meta["orientation_from"]
    # float32 sform in NIfTI-1: the affine holds to float32 precision, 1e-5 of its values
    np.testing.assert_allclose(volume.index_to_world, np.diag([-1, -1, 1, 1]) @ AFFINE_RAS, atol=1e-5)
    _check_voxels(volume, data, np.asarray(image.header.get_sform()), scale=(0.5, -100.0))


def test_nifti_qform_is_used_without_an_sform(tmp_path: Path) -> None:
    data = _data_ijk(1)
    affine = np.diag([0.5, 0.6, 2.0, 1.0])
    affine[:3, 3] = (5.0, -7.0, 11.0)
    image = nib.Nifti1Image(data, affine)
    image.set_sform(affine, code=0)
    image.set_qform(affine, code=1)
    nib.save(image, tmp_path / "q.nii")
    volume = read_volume_file(tmp_path / "q.nii")
    assert "qform" in volume.meta["orientation_from"]
    _check_voxels(volume, data, np.asarray(image.header.get_qform()))


def test_nifti_without_orientation_is_refused(tmp_path: Path) -> None:
    image = nib.Nifti1Image(_data_ijk(), AFFINE_RAS)
    image.set_sform(AFFINE_RAS, code=0)
    image.set_qform(AFFINE_RAS, code=0)
    nib.save(image, tmp_path / "bare.nii")
    with pytest.raises(VolumeFileError, match=r"bare\.nii: no orientation: sform_code and qform_code are both 0"):
        read_volume_file(tmp_path / "bare.nii")


@pytest.mark.parametrize(
    ("shape", "message"),
    [((4, 5), "a 2-D image"), ((4, 5, 1), "a 2-D image"), ((4, 5, 6, 3), "4-D data")],
)
def test_nifti_of_the_wrong_dimension_is_refused(tmp_path: Path, shape: tuple[int, ...], message: str) -> None:
    nib.save(nib.Nifti1Image(np.zeros(shape, dtype=np.int16), np.eye(4)), tmp_path / "x.nii")
    with pytest.raises(VolumeFileError, match=message):
        read_volume_file(tmp_path / "x.nii")


def test_nifti_with_one_time_point_is_a_volume(tmp_path: Path) -> None:
    data = _data_ijk()
    nib.save(nib.Nifti1Image(data[..., None], AFFINE_RAS), tmp_path / "t.nii")
    _check_voxels(read_volume_file(tmp_path / "t.nii"), data, AFFINE_RAS.astype(np.float32).astype(np.float64))


def _nrrd(path: Path, data_ijk: np.ndarray, space: str | None, directions: np.ndarray, origin: np.ndarray) -> Path:
    lines = ["NRRD0004", "type: int16", "dimension: 3"]
    if space is not None:
        lines.append(f"space: {space}")
    lines.append("sizes: " + " ".join(str(n) for n in data_ijk.shape))
    if space is not None:
        lines.append(
            "space directions: " + " ".join("(" + ",".join(repr(float(x)) for x in d) + ")" for d in directions)
        )
        lines.append("space origin: (" + ",".join(repr(float(x)) for x in origin) + ")")
    lines += ["endian: little", "encoding: raw", "", ""]
    # NRRD's first axis is the fastest: i, so the bytes are data[k, j, i] in C order
    path.write_bytes("\n".join(lines).encode() + np.ascontiguousarray(data_ijk.transpose(2, 1, 0)).tobytes())
    return path


@pytest.mark.parametrize("space", ["right-anterior-superior", "left-posterior-superior", "RAS"])
def test_nrrd_states_its_space(tmp_path: Path, space: str) -> None:
    data = _data_ijk(2)
    directions = AFFINE_RAS[:3, :3].T  # NRRD lists one vector per axis
    volume = dicom.read_volume(_nrrd(tmp_path / "v.nrrd", data, space, directions, AFFINE_RAS[:3, 3]))
    assert volume.meta["format"] == "NRRD"
    file_frame = AFFINE_RAS if space.upper().startswith(("R", "RAS")) else np.diag([-1, -1, 1, 1]) @ AFFINE_RAS
    _check_voxels(volume, data, file_frame)


@pytest.mark.parametrize(("space", "message"), [(None, "no 'space' field"), ("scanner-xyz", "not a patient frame")])
def test_nrrd_without_a_patient_space_is_refused(tmp_path: Path, space: str | None, message: str) -> None:
    path = _nrrd(tmp_path / "v.nrrd", _data_ijk(), space, np.eye(3), np.zeros(3))
    with pytest.raises(VolumeFileError, match=message):
        read_volume_file(path)


@pytest.mark.parametrize("suffix", [".nii", ".nii.gz", ".nrrd", ".mha"])
def test_written_files_read_back_to_the_same_volume(tmp_path: Path, suffix: str) -> None:
    lps = np.diag([-1, -1, 1, 1]) @ AFFINE_RAS
    volume = Volume(np.random.default_rng(3).normal(size=(6, 5, 4)).astype(np.float32), lps, label="x")
    back = read_volume_file(write_volume_file(volume, tmp_path / f"v{suffix}"))
    np.testing.assert_array_equal(back.data, volume.data)
    # NIfTI-1 keeps its affine in float32; NRRD and MetaImage print float64
    np.testing.assert_allclose(back.index_to_world, volume.index_to_world, atol=1e-5 if "nii" in suffix else 1e-12)
    assert not list(tmp_path.glob(".*partial*"))
    if "nii" in suffix:  # another tool reads the project's NIfTI in RAS with data[i, j, k]
        other = nib.load(tmp_path / f"v{suffix}")
        np.testing.assert_allclose(other.affine, AFFINE_RAS, atol=1e-5)
        np.testing.assert_array_equal(np.asarray(other.dataobj), volume.data.transpose(2, 1, 0))


def test_not_a_volume_file(tmp_path: Path) -> None:
    (tmp_path / "junk.nii").write_bytes(b"not nifti at all" * 40)
    with pytest.raises(VolumeFileError, match="not a readable NIfTI file"):
        read_volume_file(tmp_path / "junk.nii")
    (tmp_path / "junk.mha").write_text("ObjectType = Image\nNDims = 3\n")
    with pytest.raises(VolumeFileError, match="junk.mha"):
        read_volume_file(tmp_path / "junk.mha")
