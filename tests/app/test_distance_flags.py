"""``--sid-mm``/``--sod-mm`` for ``app --volume --image``, ``validate rotational-run`` and ``listen``:
a file lacking DistanceSourceToDetector is accepted with the flag and refused, naming the flag,
without it (as ``register`` and ``track``)."""

from __future__ import annotations

from pathlib import Path

import pytest

from app.cli.net_commands import _Registrar
from registration.io import dicom
from registration.io.node import Received
from tests.app.test_commands import run

#: Not the export's SID (its C-arm's), so the value read back can only come from the flag.
SID_MM = 1150.0


def _without_sid(source: Path, target: Path) -> Path:
    ds = dicom.read_dataset(source)
    assert "DistanceSourceToDetector" in ds
    del ds.DistanceSourceToDetector
    ds.save_as(target)
    return target


@pytest.fixture(scope="module")
def nosid(small_export: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("nosid")
    image = dicom.read_xray(small_export / "xa_fluoro.dcm")
    run_file = dicom.write_xray_run([image] * 3, folder / "run-sid.dcm", times_s=[0.0, 0.1, 0.2])
    return {
        "volume": small_export / "volume",
        "image": _without_sid(small_export / "xa_fluoro.dcm", folder / "image.dcm"),
        "run": _without_sid(run_file, folder / "run.dcm"),
    }


class _Served(ValueError):
    """Raised instead of serving: the data was read."""


def test_app_image_distances(nosid: dict[str, Path], monkeypatch: pytest.MonkeyPatch, capsys) -> None:
    import app.web.main

    read: list[float] = []

    def no_server(*_a: object, **_k: object) -> None:
        raise _Served("served")

    original = app.web.main.FileData.from_paths

    def from_paths(*a: object, **k: object) -> object:
        data = original(*a, **k)
        read.append(data.fixed_xray.geometry.sid_mm)
        return data

    monkeypatch.setattr(app.web.main, "make_server", no_server)
    monkeypatch.setattr(app.web.main.FileData, "from_paths", from_paths)
    args = ["app", "--volume", str(nosid["volume"]), "--image", str(nosid["image"])]
    code, _, err = run(args, capsys)
    assert code == 2 and "DistanceSourceToDetector (0018,1110)" in err and "--sid-mm" in err
    code, _, err = run([*args, "--sid-mm", str(SID_MM)], capsys)
    assert code == 2 and "served" in err and read == [SID_MM]  # read, then (here) not served
    code, _, err = run(["app", "--sid-mm", str(SID_MM)], capsys)
    assert code == 2 and "--sid-mm/--sod-mm apply to --volume/--image" in err


def test_rotational_run_distances(nosid: dict[str, Path], monkeypatch: pytest.MonkeyPatch, capsys,
                                  tmp_path: Path) -> None:  # fmt: skip
    import registration.studies.rotational as rotational

    seen: list[float] = []

    def validate(volume: object, xrun: dicom.XRayRun, *_a: object, **_k: object) -> list:
        seen.extend(g.sid_mm for g in xrun.geometries)
        raise _Served("validated")  # the registrations themselves are tested in test_rotational.py

    monkeypatch.setattr(rotational, "validate_rotational_run", validate)
    args = ["validate", "rotational-run", "--volume", str(nosid["volume"]), "--run", str(nosid["run"]),
            "--cases", "1", "--out", str(tmp_path / "out")]  # fmt: skip
    code, _, err = run(args, capsys)
    assert code == 2 and "DistanceSourceToDetector (0018,1110)" in err and "--sid-mm" in err
    code, _, err = run([*args, "--sid-mm", str(SID_MM)], capsys)
    assert code == 2 and "validated" in err and seen == [SID_MM] * 3


def test_listen_distances(nosid: dict[str, Path], tmp_path: Path, capsys) -> None:
    code, _, err = run(["listen", "--allow", "CARM", "--port", "0", "--sid-mm", str(SID_MM)], capsys)
    assert code == 2 and "--sid-mm/--sod-mm apply to the images registered with --volume" in err

    def item(path: Path, frames: int) -> Received:
        return Received(path, "CARM", "1.2.840.10008.5.1.4.1.1.12.1", "1.2", "1.2.3", "XA", frames)

    refusing = _Registrar(nosid["volume"], tmp_path / "a")
    accepting = _Registrar(nosid["volume"], tmp_path / "b", sid_mm=SID_MM)
    try:
        for path, frames in ((nosid["image"], 1), (nosid["run"], 3)):
            with pytest.raises(ValueError, match="--sid-mm"):
                refusing.read(item(path, frames))
            images = accepting.read(item(path, frames))
            assert [x.geometry.sid_mm for x in images] == [SID_MM] * frames
    finally:
        refusing.close()
        accepting.close()
