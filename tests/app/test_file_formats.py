"""``roadmap3d register`` with NIfTI/NRRD/MetaImage volumes and TIFF/PNG images.

The twins: a NIfTI written from the real head CT (../shared/data/real-ct, outside the
repository; skipped without it) and a TIFF with its geometry side file written from an XA must
register to the same pose as the DICOM series and the DICOM XA (the same numbers reach the same
deterministic engine: 1e-6 mm). Bad files end with ``error: ...`` and exit code 2.
"""

from __future__ import annotations

import json
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest

from registration.io import dicom
from registration.io.image_files import write_image_file
from registration.io.volume_files import write_volume_file
from tests.app.test_commands import SMALL, run


@pytest.fixture(scope="module")
def phantom(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from app import cli

    out = tmp_path_factory.mktemp("export") / "phantom"
    with pytest.raises(SystemExit) as info:
        cli.main(["phantom", "--out", str(out), "--primary-deg", "20", "--secondary-deg", "-10", *SMALL])
    assert info.value.code == 0
    return out


def test_bad_volume_and_image_files_exit_2(phantom: Path, tmp_path: Path, capsys) -> None:
    image = next(phantom.glob("*.dcm"))
    bare = nib.Nifti1Image(np.zeros((8, 8, 8), dtype=np.int16), np.eye(4))
    bare.set_sform(np.eye(4), code=0)
    bare.set_qform(np.eye(4), code=0)
    nib.save(bare, tmp_path / "bare.nii")
    code, _, err = run(["register", "--volume", str(tmp_path / "bare.nii"), "--image", str(image)], capsys)
    assert code == 2 and "error:" in err and "no orientation" in err
    nib.save(nib.Nifti1Image(np.zeros((8, 8), dtype=np.int16), np.eye(4)), tmp_path / "flat.nii")
    code, _, err = run(["register", "--volume", str(tmp_path / "flat.nii"), "--image", str(image)], capsys)
    assert code == 2 and "a 2-D image" in err
    (tmp_path / "x.tif").write_bytes(b"II*\x00garbage")
    volume = next(p for p in phantom.iterdir() if p.is_dir())
    code, _, err = run(["register", "--volume", str(volume), "--image", str(tmp_path / "x.tif")], capsys)
    assert code == 2 and "no such geometry file" in err
    code, _, err = run(["register", "--volume", str(volume), "--image", str(image), "--out-transform",
                        str(tmp_path / "r.json")], capsys)  # fmt: skip
    assert code == 2 and "--out-transform takes an ITK transform file" in err
    code, _, err = run(["register", "--volume", str(volume), "--image", str(image), "--geometry", "a.json",
                        "--geometry", "b.json"], capsys)  # fmt: skip
    assert code == 2 and "one side file per --image" in err


def test_out_transform_reads_back_as_the_motion(phantom: Path, tmp_path: Path, capsys, monkeypatch) -> None:
    from registration.io.transforms import read_itk_transform

    monkeypatch.setenv("ROADMAP3D_CACHE", str(tmp_path / "cache"))
    volume = next(p for p in phantom.iterdir() if p.is_dir())
    argv = ["register", "--volume", str(volume), "--image", str(phantom / "xa_fluoro.dcm"), "--out",
            str(tmp_path / "r.json"), "--out-transform", str(tmp_path / "r.h5")]  # fmt: skip
    code, out, err = run(argv, capsys)
    assert code == 0, err
    motion = np.asarray(json.loads((tmp_path / "r.json").read_text())["patient_motion"])
    # the HDF5 file holds float64: the motion comes back to rounding
    np.testing.assert_allclose(read_itk_transform(tmp_path / "r.h5"), motion, atol=1e-9)
    assert "ITK transform" in out


def _find_ct() -> Path | None:
    from registration.studies.volume import find_real_ct

    return find_real_ct()


@pytest.mark.slow
def test_nifti_and_tiff_twins_register_like_dicom(tmp_path: Path, capsys, monkeypatch) -> None:
    from registration.studies.volume import (
        REAL_CT_RELATIVE,
        VolumeImager,
        VolumeStudyConfig,
        _views,
        case_motion,
        volume_cases,
    )

    ct = _find_ct()
    if ct is None:
        pytest.skip(f"the real head CT is not here ({REAL_CT_RELATIVE} beside the project)")
    monkeypatch.setenv("ROADMAP3D_CACHE", str(tmp_path / "cache"))
    volume = dicom.read_volume(ct)
    iso = (247.5, -276.0, -90.0)  # the studies' iso-center inside the skull (head_isocenter_mm)
    config = VolumeStudyConfig(cases=1, seed=0)
    case = volume_cases(config)[0]
    truth = case_motion(case, iso)
    image = VolumeImager(volume, iso).image(_views(config, case, iso)[0], truth, kind=config.kind, seed=case.seed)
    xa = dicom.write_xray(image, tmp_path / "xa.dcm", description="fluoro formed from the CT (test)")
    _, side = write_image_file(dicom.read_xray(xa), tmp_path / "xa.tif")
    side = side.rename(tmp_path / "geometry.json")  # given with --geometry, not found by name
    write_volume_file(volume, tmp_path / "ct.nii")
    poses = {}
    runs = (("dicom", ct, xa, []), ("nifti+tiff", tmp_path / "ct.nii", tmp_path / "xa.tif", ["--geometry", str(side)]))
    for name, vol, img, extra in runs:
        out = tmp_path / f"{name}.json"
        argv = ["register", "--volume", str(vol), "--image", str(img), "--isocenter", "247.5,-276,-90",
                "--out", str(out), *extra]  # fmt: skip
        code, _, err = run(argv, capsys)
        assert code == 0, err
        poses[name] = np.asarray(json.loads(out.read_text())["patient_motion"])
    # the same voxels, affine, line integrals, mask and geometry: the same deterministic result
    assert np.max(np.abs(poses["dicom"] - poses["nifti+tiff"])) <= 1e-6
    # and through the Python API
    import registration

    api = {
        "dicom": registration.register(
            registration.Volume.from_dicom(ct), registration.XRayImage.from_dicom(xa, isocenter_mm=iso)
        ),
        "nifti+tiff": registration.register(
            registration.Volume.from_file(tmp_path / "ct.nii"),
            registration.XRayImage.from_file(tmp_path / "xa.tif", side, isocenter_mm=iso),
        ),
    }
    assert np.max(np.abs(api["dicom"].patient_motion - api["nifti+tiff"].patient_motion)) <= 1e-6
    # and a registration worth comparing: the images were formed from the CT itself (a best case)
    c = np.array([*iso, 1.0])
    assert np.linalg.norm((poses["dicom"] @ np.linalg.inv(truth) @ c - c)[:3]) < 5.0  # residual at the iso-center
