"""The PACS over DICOMweb (registration/io/pacs.py) against a real Orthanc (tests/orthanc.py).

The phantom's DICOM export is stored with STOW-RS, found with QIDO-RS and retrieved with
WADO-RS; what comes back must read as exactly what was exported. The settings tests need no
server: credentials never come from a URL, never cross plain HTTP to another machine, and a
readable config file holding a password is refused.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from registration.io import dicom
from registration.io.pacs import Pacs, PacsError, PacsSettings, find_series
from tests.orthanc import OrthancServer


# --------------------------------------------------------------------------------------
# Settings (no server)
# --------------------------------------------------------------------------------------
def test_credentials_in_the_url_are_refused() -> None:
    with pytest.raises(PacsError, match="credentials in the URL") as info:
        PacsSettings("https://alice:s3cret@pacs.example.org/dicom-web")
    assert "s3cret" not in str(info.value)


def test_credentials_never_cross_plain_http_to_another_machine() -> None:
    with pytest.raises(PacsError, match="plain HTTP"):
        PacsSettings("http://pacs.example.org/dicom-web", username="a", password="b")
    # loopback and https are fine
    PacsSettings("http://127.0.0.1:8042/dicom-web", username="a", password="b")
    PacsSettings("https://pacs.example.org/dicom-web", username="a", password="b")


def test_password_not_in_repr_and_ca_bundle_checked(tmp_path: Path) -> None:
    s = PacsSettings("https://pacs.example.org/dicom-web", username="alice", password="s3cret")
    assert "s3cret" not in repr(s) and "alice" in repr(s)
    with pytest.raises(PacsError, match="no such file"):
        PacsSettings("https://pacs.example.org/x", ca_bundle=tmp_path / "missing.pem")
    with pytest.raises(PacsError, match="https"):
        (tmp_path / "ca.pem").write_text("x")
        PacsSettings("http://127.0.0.1/x", ca_bundle=tmp_path / "ca.pem")


def test_resolve_from_environment_and_config(tmp_path: Path) -> None:
    config = tmp_path / "pacs.json"
    entries = [
        {"url": "https://a.example.org/dw", "username": "ua", "password": "pa"},
        {"url": "https://b.example.org/dw", "username": "ub", "password": "pb"},
    ]
    config.write_text(json.dumps(entries))
    config.chmod(0o644)
    with pytest.raises(PacsError, match="chmod 600"):
        PacsSettings.resolve("https://b.example.org/dw", config=config, environ={})
    config.chmod(0o600)
    s = PacsSettings.resolve("https://b.example.org/dw/", config=config, environ={})
    assert (s.username, s.password) == ("ub", "pb")
    env = {"ROADMAP3D_PACS_USERNAME": "envuser", "ROADMAP3D_PACS_PASSWORD": "envpass"}
    s = PacsSettings.resolve("https://a.example.org/dw", config=config, environ=env)
    assert (s.username, s.password) == ("envuser", "envpass")
    with pytest.raises(PacsError, match="no PACS URL"):
        PacsSettings.resolve(None, config=config, environ={})


# --------------------------------------------------------------------------------------
# Against Orthanc
# --------------------------------------------------------------------------------------
@pytest.fixture()
def export(small_export: Path) -> Path:
    return small_export


@pytest.fixture()
def pacs(orthanc: OrthancServer) -> Pacs:
    orthanc.clear()
    return Pacs(PacsSettings(orthanc.dicomweb_url, username=orthanc.username, password=orthanc.password))


def _files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.rglob("*.dcm"))


def test_store_list_retrieve_round_trip(pacs: Pacs, export: Path, tmp_path: Path) -> None:
    files = _files(export)
    assert pacs.store(files) == len(files)

    patients = pacs.patients()
    assert [(p.patient_id, p.studies) for p in patients] == [("ROADMAP3D", 1)]
    studies = pacs.studies(patient_id="ROADMAP3D")
    assert len(studies) == 1 and set(studies[0].modalities) >= {"CT", "XA"}
    series = pacs.series(studies[0].study_uid)
    volume_series = find_series(series, "volume")
    assert volume_series is not None and volume_series.modality == "CT"
    assert volume_series.instances == len(_files(export / "volume"))
    xrays = [s for s in series if s.role == "xray"]
    assert len(xrays) == 3  # plane A's fluoro and exposure, plane B's fluoro
    assert sum("plane b" in s.description.lower() for s in xrays) == 1

    folder = pacs.retrieve_series(studies[0].study_uid, volume_series.series_uid, tmp_path / "vol")
    assert (folder.stat().st_mode & 0o777) == 0o700
    assert all((p.stat().st_mode & 0o777) == 0o600 for p in folder.iterdir())
    got = dicom.read_volume(folder)
    want = dicom.read_volume(export / "volume")
    # the same stored integers travel both ways: bit-identical HU and affine
    assert np.array_equal(got.data, want.data)
    assert np.allclose(got.index_to_world, want.index_to_world, atol=1e-9)

    fluoro = next(s for s in xrays if "fluoro" in s.description and "plane b" not in s.description.lower())
    xfolder = pacs.retrieve_series(studies[0].study_uid, fluoro.series_uid)
    try:
        (image_file,) = list(xfolder.iterdir())
        got_x = dicom.read_xray(image_file)
        want_x = dicom.read_xray(export / "xa_fluoro.dcm")
        assert np.array_equal(got_x.image, want_x.image) and np.array_equal(got_x.mask, want_x.mask)
        assert got_x.geometry == want_x.geometry
    finally:
        for p in xfolder.iterdir():
            p.unlink()
        xfolder.rmdir()


def test_wrong_password_is_a_clear_error(orthanc: OrthancServer) -> None:
    bad = Pacs(PacsSettings(orthanc.dicomweb_url, username=orthanc.username, password="wrong-password"))
    with pytest.raises(PacsError, match="HTTP 401 .wrong or missing credentials") as info:
        bad.studies()
    assert "wrong-password" not in str(info.value)


def test_unreachable_server_is_a_clear_error() -> None:
    from tests.orthanc import free_port

    pacs = Pacs(PacsSettings(f"http://127.0.0.1:{free_port()}/dicom-web", timeout_s=(1.0, 1.0), attempts=1))
    with pytest.raises(PacsError, match="cannot connect"):
        pacs.studies()


def test_https_verifies_the_server_against_the_ca_bundle(orthanc: OrthancServer, tmp_path: Path) -> None:
    """HTTPS (self-signed certificate for 127.0.0.1, tests/orthanc.TlsProxy in front of the real
    Orthanc): refused without the CA bundle, served with it."""
    import shutil as _shutil

    from tests.orthanc import TlsProxy

    if _shutil.which("openssl") is None:
        pytest.skip("the openssl command is not installed (apt-get install openssl)")
    orthanc.clear()
    proxy = TlsProxy(orthanc.http_port, tmp_path)
    try:
        url = f"https://127.0.0.1:{proxy.port}/dicom-web"
        blind = Pacs(PacsSettings(url, username=orthanc.username, password=orthanc.password, attempts=1))
        with pytest.raises(PacsError, match="certificate is not trusted"):
            blind.studies()
        trusting = Pacs(
            PacsSettings(url, username=orthanc.username, password=orthanc.password, ca_bundle=proxy.certificate)
        )
        assert trusting.studies() == []
    finally:
        proxy.close()


def test_a_series_over_the_byte_bound_is_refused_and_removed(
    pacs: Pacs, export: Path, tmp_path: Path, monkeypatch
) -> None:
    import registration.io.pacs as pacs_module

    pacs.store(sorted((export / "volume").iterdir()))
    (study,) = pacs.studies()
    (series,) = pacs.series(study.study_uid)
    monkeypatch.setattr(pacs_module, "MAX_SERIES_BYTES", 10_000)  # a few slices of 48x48 int16
    monkeypatch.setattr(pacs_module.tempfile, "tempdir", str(tmp_path))
    with pytest.raises(PacsError, match="exceeds 10000 bytes; refused"):
        pacs.retrieve_series(study.study_uid, series.series_uid)
    assert list(tmp_path.iterdir()) == []  # the private temporary folder is gone
