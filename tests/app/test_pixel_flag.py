"""--pixel-mm: a real XA without ImagerPixelSpacing is read with the spacing the user gives."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from app import cli

#: ``../shared/data/real-xa`` beside the project, or ``$ROADMAP3D_SHARED_DATA/real-xa``.
REAL_XA = (
    Path(os.environ.get("ROADMAP3D_SHARED_DATA") or Path(__file__).resolve().parents[3] / "shared" / "data")
    / "real-xa"
    / "coronary-xa-96-frames.dcm"
)


def _run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    with pytest.raises(SystemExit) as info:
        cli.main(argv)
    out, err = capsys.readouterr()
    assert "Traceback" not in err
    return int(info.value.code or 0), out, err


def test_a_real_xa_without_pixel_spacing_is_read_with_the_flag(capsys) -> None:
    if not REAL_XA.exists():
        pytest.skip(f"{REAL_XA} is absent (the real X-ray files live in ../shared/data/real-xa)")
    distances = ["--sid-mm", "1000", "--sod-mm", "750"]
    code, _, err = _run(["info", str(REAL_XA), *distances], capsys)
    assert code == 2 and "ImagerPixelSpacing" in err and "--pixel-mm" in err  # refused, and told how
    code, out, err = _run(["info", str(REAL_XA), *distances, "--pixel-mm", "0.3"], capsys)
    assert code == 0, err
    assert "512x512 px of 0.3x0.3 mm" in out
    from registration.io import dicom

    image = dicom.read_xray(REAL_XA, frame=3, sid_mm=1000.0, sod_mm=750.0, pixel_mm=0.3)
    assert image.geometry.pixel_mm == (0.3, 0.3)
    with pytest.raises(ValueError, match="--pixel-mm"):
        dicom.read_xray(REAL_XA, frame=3, sid_mm=1000.0, sod_mm=750.0)
    with pytest.raises(ValueError, match="positive"):
        dicom.read_xray(REAL_XA, frame=3, sid_mm=1000.0, sod_mm=750.0, pixel_mm=-1.0)


def test_a_real_run_without_pixel_spacing_is_read_with_the_flag() -> None:
    """The same file as a run (what track and listen read): every frame's geometry has the spacing."""
    if not REAL_XA.exists():
        pytest.skip(f"{REAL_XA} is absent (the real X-ray files live in ../shared/data/real-xa)")
    from registration.io import dicom

    run = dicom.read_xray_run(REAL_XA, sid_mm=1000.0, sod_mm=750.0, pixel_mm=0.3)
    assert len(run) == 96 and all(g.pixel_mm == (0.3, 0.3) for g in run.geometries)
    assert run[5].geometry.pixel_mm == (0.3, 0.3)  # a frame read later keeps it
    with pytest.raises(ValueError, match="--pixel-mm"):
        dicom.read_xray_run(REAL_XA, sid_mm=1000.0, sod_mm=750.0)
