"""``roadmap3d register --pacs``: against a real Orthanc, the issue's round trip.

The phantom's export is stored into Orthanc (STOW-RS); the study is listed (QIDO-RS); the 3DRA
series and the fluoro image are loaded from it (WADO-RS) and registered; the Spatial
Registration object and the overlay (Secondary Capture) are stored back into the study; the
REG object read back from Orthanc holds exactly the motion the registration wrote.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pydicom
import pytest

from app import cli
from registration.io import dicom
from registration.io.pacs import Pacs, PacsSettings
from tests.orthanc import OrthancServer


def _run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    with pytest.raises(SystemExit) as info:
        cli.main(argv)
    out, err = capsys.readouterr()
    assert "Traceback" not in err
    return int(info.value.code or 0), out, err


@pytest.mark.slow  # a whole registration
def test_register_from_pacs_and_store_back(
    orthanc: OrthancServer, small_export: Path, tmp_path: Path, capsys, monkeypatch
) -> None:
    orthanc.clear()
    pacs = Pacs(PacsSettings(orthanc.dicomweb_url, username=orthanc.username, password=orthanc.password))
    pacs.store(sorted(small_export.rglob("*.dcm")))
    (study,) = pacs.studies()
    series = pacs.series(study.study_uid)
    volume = next(s for s in series if s.role == "volume")
    # plane A's fluoro (the export also holds plane B's, described as such, and the exposure)
    fluoro = next(
        s for s in series if s.role == "xray" and "fluoro" in s.description and "plane b" not in s.description.lower()
    )

    # credentials only through the environment
    monkeypatch.setenv("ROADMAP3D_PACS_USERNAME", orthanc.username)
    monkeypatch.setenv("ROADMAP3D_PACS_PASSWORD", orthanc.password)
    monkeypatch.setenv("ROADMAP3D_PACS_CONFIG", str(tmp_path / "no-config.json"))
    result_json = tmp_path / "result.json"
    argv = ["register", "--pacs", orthanc.dicomweb_url, "--study", study.study_uid, "--volume", volume.series_uid,
            "--image", fluoro.series_uid, "--truth", str(small_export / "truth.json"), "--out", str(result_json),
            "--store"]  # fmt: skip
    code, out, err = _run(argv, capsys)
    assert code == 0, err
    assert orthanc.password not in out + err
    assert "stored on" in out and "Secondary Capture" in out

    # the study now also holds the REG object and the capture
    after = pacs.series(study.study_uid)
    assert len(after) == len(series) + 2
    reg_series = next(s for s in after if s.modality == "REG")
    capture_series = next(s for s in after if s.modality == "OT")
    folder = pacs.retrieve_series(study.study_uid, reg_series.series_uid, tmp_path / "reg")
    (reg_file,) = list(folder.iterdir())
    reg = dicom.read_registration(reg_file)
    written = np.asarray(json.loads(result_json.read_text())["patient_motion"])
    # The REG object stores the matrix as decimal strings (DS, 16 characters): ~1e-10 relative.
    assert np.allclose(reg.patient_motion, written, atol=1e-6)

    capture_folder = pacs.retrieve_series(study.study_uid, capture_series.series_uid, tmp_path / "sc")
    (capture_file,) = list(capture_folder.iterdir())
    sc = pydicom.dcmread(capture_file)
    xa = pydicom.dcmread(small_export / "xa_fluoro.dcm")
    assert sc.SOPClassUID == pydicom.uid.SecondaryCaptureImageStorage
    assert (sc.Rows, sc.Columns, sc.SamplesPerPixel) == (xa.Rows, xa.Columns, 3)
    assert sc.SourceImageSequence[0].ReferencedSOPInstanceUID == xa.SOPInstanceUID
    rgb = sc.pixel_array
    red = (rgb[..., 0].astype(int) - rgb[..., 1]) > 60
    # the registered vessels are drawn (red) inside the field, nowhere outside it
    field = dicom.read_xray(small_export / "xa_fluoro.dcm").mask
    assert red[field].sum() > 20 and red[~field].sum() == 0
    # an X-ray reader refuses the capture: it cannot be mistaken for an acquisition
    with pytest.raises(ValueError):
        dicom.read_xray(capture_file)


def test_register_pacs_needs_a_study_and_refuses_url_credentials(capsys) -> None:
    code, _, err = _run(["register", "--volume", "1.2", "--image", "1.3", "--store"], capsys)
    assert code == 2 and "need --pacs" in err
    code, _, err = _run(["register", "--pacs", "https://u:secret@pacs.example.org/dw", "--study", "1.2",
                         "--volume", "1.2", "--image", "1.3"], capsys)  # fmt: skip
    assert code == 2 and "credentials in the URL are refused" in err and "secret" not in err
    code, _, err = _run(["register", "--pacs", "https://pacs.example.org/dw", "--study", "1.2",
                         "--volume", "1.2", "--image", "1.3", "--confidence"], capsys)  # fmt: skip
    assert code == 2 and "--confidence" in err and "on files only" in err


def test_track_from_pacs(orthanc: OrthancServer, small_export: Path, tmp_path: Path, capsys, monkeypatch) -> None:
    """``track --pacs``: the run comes from the PACS (here the export's fluoro image: a run of one frame)."""
    orthanc.clear()
    pacs = Pacs(PacsSettings(orthanc.dicomweb_url, username=orthanc.username, password=orthanc.password))
    pacs.store(sorted(small_export.rglob("*.dcm")))
    (study,) = pacs.studies()
    series = pacs.series(study.study_uid)
    volume = next(s for s in series if s.role == "volume")
    # plane A's fluoro (the export also holds plane B's, described as such, and the exposure)
    fluoro = next(
        s for s in series if s.role == "xray" and "fluoro" in s.description and "plane b" not in s.description.lower()
    )
    monkeypatch.setenv("ROADMAP3D_PACS_USERNAME", orthanc.username)
    monkeypatch.setenv("ROADMAP3D_PACS_PASSWORD", orthanc.password)
    out = tmp_path / "track.json"
    code, _, err = _run(["track", "--pacs", orthanc.dicomweb_url, "--study", study.study_uid, "--volume",
                         volume.series_uid, "--run", fluoro.series_uid, "--out", str(out)], capsys)  # fmt: skip
    assert code == 0, err
    doc = json.loads(out.read_text())
    frames = doc["frames"] if isinstance(doc, dict) and "frames" in doc else doc
    assert len(frames) == 1
    code, _, err = _run(["track", "--pacs", orthanc.dicomweb_url, "--study", study.study_uid, "--volume",
                         volume.series_uid, "--run", "1.2.3.4"], capsys)  # fmt: skip
    assert code == 2 and "has no series 1.2.3.4 (--run)" in err


@pytest.mark.slow  # two small volume studies of one case each
def test_validate_volume_from_pacs(orthanc: OrthancServer, small_export: Path, tmp_path: Path, capsys,
                                   monkeypatch) -> None:  # fmt: skip
    """``validate volume --pacs URL --study UID --volume SERIES``: the series retrieved over WADO-RS
    gives the same study as the export's folder (same seed: the same volume gives the same numbers)."""
    orthanc.clear()
    pacs = Pacs(PacsSettings(orthanc.dicomweb_url, username=orthanc.username, password=orthanc.password))
    pacs.store(sorted((small_export / "volume").rglob("*.dcm")))
    (study,) = pacs.studies()
    (volume,) = [s for s in pacs.series(study.study_uid) if s.role == "volume"]
    monkeypatch.setenv("ROADMAP3D_PACS_USERNAME", orthanc.username)
    monkeypatch.setenv("ROADMAP3D_PACS_PASSWORD", orthanc.password)
    monkeypatch.setenv("ROADMAP3D_PACS_CONFIG", str(tmp_path / "no-config.json"))
    common = ["--isocenter", "volume-center", "--cases", "1", "--json", "--seed", "3"]
    code, out, err = _run(["validate", "volume", "--volume", str(small_export / "volume"), *common], capsys)
    assert code == 0, err
    local = json.loads(out)
    pacs_args = ["validate", "volume", "--pacs", orthanc.dicomweb_url, "--study", study.study_uid]
    code, out, err = _run([*pacs_args, "--volume", volume.series_uid, *common], capsys)
    assert code == 0, err
    assert "retrieving" in err and orthanc.password not in out + err
    remote = json.loads(out)
    assert remote["runs"] == local["runs"] == 1
    for key in ("inplane_residual_mm_median", "rotation_residual_deg_median", "success_rate"):
        assert remote[key] == local[key], key
    code, _, err = _run([*pacs_args, "--volume", "1.2.3.4", *common], capsys)
    assert code == 2 and "has no series 1.2.3.4 (--volume)" in err
    code, _, err = _run(["validate", "volume", "--volume", str(small_export / "volume"), "--study", "1.2"], capsys)
    assert code == 2 and "--study applies to --pacs only" in err


@pytest.fixture(scope="module")
def biplane_run_export(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``roadmap3d phantom-run --biplane``: 2 s at 64 px, both planes' runs and the 3DRA series."""
    out = tmp_path_factory.mktemp("biplane-run") / "phantom-run"
    with pytest.raises(SystemExit) as info:
        cli.main(["phantom-run", "--out", str(out), "--biplane", "--pixels", "64", "--voxels", "128",
                  "--volume-source", "resampled", "--seconds", "2", "--sudden-moves", "1"])  # fmt: skip
    assert info.value.code == 0
    return out


def test_track_a_biplane_pair_from_pacs(
    orthanc: OrthancServer, biplane_run_export: Path, tmp_path: Path, capsys, monkeypatch
) -> None:
    """``track --pacs --run A --run-b B``: both planes' runs retrieved from the study and tracked
    together, frame for frame what the same files give from disk (the same bytes, the same seed)."""
    from app.cli import track_commands as tc

    export = biplane_run_export
    orthanc.clear()
    pacs = Pacs(PacsSettings(orthanc.dicomweb_url, username=orthanc.username, password=orthanc.password))
    pacs.store(sorted(export.rglob("*.dcm")))
    (study,) = pacs.studies()
    series = pacs.series(study.study_uid)
    volume = next(s for s in series if s.role == "volume")
    plane = {s.description.split()[-1]: s for s in series if "fluoro run" in s.description}
    assert sorted(plane) == ["A", "B"], [s.description for s in series]
    monkeypatch.setenv("ROADMAP3D_PACS_USERNAME", orthanc.username)
    monkeypatch.setenv("ROADMAP3D_PACS_PASSWORD", orthanc.password)
    monkeypatch.setenv("ROADMAP3D_PACS_CONFIG", str(tmp_path / "no-config.json"))
    common = ["--truth", str(export / tc.RUN_TRUTH), "--every-frame", "--seed", "1"]

    code, _, err = _run(["track", "--volume", str(export / tc.RUN_VOLUME_DIR), "--run", str(export / tc.RUN_FILE),
                         "--run-b", str(export / tc.RUN_B_FILE), "--out", str(tmp_path / "local.json"), *common],
                        capsys)  # fmt: skip
    assert code == 0, err
    pacs_args = ["track", "--pacs", orthanc.dicomweb_url, "--study", study.study_uid, "--volume", volume.series_uid]
    code, out, err = _run([*pacs_args, "--run", plane["A"].series_uid, "--run-b", plane["B"].series_uid,
                           "--out", str(tmp_path / "pacs.json"), *common], capsys)  # fmt: skip
    assert code == 0, err
    assert orthanc.password not in out + err
    local = json.loads((tmp_path / "local.json").read_text())
    remote = json.loads((tmp_path / "pacs.json").read_text())
    assert len(remote["runs"]) == 2 and len(remote["frames"]) == len(local["frames"]) == 30
    for a, b in zip(local["frames"], remote["frames"], strict=True):
        assert (a["frame"], a["status"]) == (b["frame"], b["status"])
        np.testing.assert_array_equal(a["patient_motion"], b["patient_motion"])  # same files, same seed: exact
    assert remote["summary"]["tracking_error_mm_median"] is not None  # scored against the truth (3-D: biplane)

    # plane A alone: tracked as one plane, with a word on the other plane's run
    code, _, err = _run([*pacs_args, "--run", plane["A"].series_uid], capsys)
    assert code == 0 and "is PLANE A of a biplane run; --run-b" in err, err

    # the planes given the other way round: plane A by its Plane Identification goes first
    code, _, err = _run([*pacs_args, "--run", plane["B"].series_uid, "--run-b", plane["A"].series_uid,
                         "--out", str(tmp_path / "swapped.json"), *common], capsys)  # fmt: skip
    assert code == 0 and "is plane A by its Plane Identification" in err, err
    swapped = json.loads((tmp_path / "swapped.json").read_text())
    assert [f["status"] for f in swapped["frames"]] == [f["status"] for f in local["frames"]]

    code, _, err = _run([*pacs_args, "--run", plane["A"].series_uid, "--run-b", plane["A"].series_uid], capsys)
    assert code == 2 and "the same series" in err
    code, _, err = _run([*pacs_args, "--run", plane["A"].series_uid, "--run-b", "1.2.3.4"], capsys)
    assert code == 2 and "has no series 1.2.3.4 (--run-b)" in err
