"""A biplane pair in DICOM (CONVENTIONS §6): planes, geometry and acquisition time round-trip;
two images of different moments, or of one plane, are refused with a clear message."""

from datetime import UTC, datetime, timedelta

import numpy as np
import pytest

from registration.core.geometry import CArm
from registration.core.images import XRayImage
from registration.io.dicom import write_xray
from registration.io.dicom.biplane import PAIR_TOLERANCE_S, read_biplane
from registration.io.dicom.xray import read_xray


def _view(geometry: CArm, seed: int) -> XRayImage:
    rng = np.random.default_rng(seed)
    mask = geometry.field_mask()
    image = np.where(mask, rng.uniform(0.5, 3.0, (geometry.rows, geometry.cols)), 0.0).astype(np.float32)
    return XRayImage(image, mask, geometry, "fluoro")


PLANE_A = CArm.for_format(27.0, pixels=64, primary_deg=-12.5, secondary_deg=4.0)
PLANE_B = CArm(primary_deg=91.0, secondary_deg=-3.0, sid_mm=1150.0, sod_mm=760.0, rows=48, cols=48, pixel_mm=(4.5, 4.5))
MOMENT = datetime(2026, 12, 1, 9, 30, 15, 250000, tzinfo=UTC)


def test_biplane_pair_round_trips(tmp_path):
    a, b = _view(PLANE_A, 1), _view(PLANE_B, 2)
    write_xray(a, tmp_path / "a.dcm", uid_seed="a", plane="PLANE A", acquired_at=MOMENT)
    write_xray(b, tmp_path / "b.dcm", uid_seed="b", plane="PLANE B", acquired_at=MOMENT + timedelta(milliseconds=30))
    # Given in the other order, the pair comes back as (plane A, plane B).
    got_a, got_b = read_biplane([tmp_path / "b.dcm", tmp_path / "a.dcm"])
    assert (got_a.meta["plane"], got_b.meta["plane"]) == ("PLANE A", "PLANE B")
    for got, want in ((got_a, a), (got_b, b)):
        g, w = got.geometry, want.geometry
        # Angles and distances are written as DICOM decimal strings (16 characters): 1e-6 is ample.
        for name in ("primary_deg", "secondary_deg", "sid_mm", "sod_mm"):
            assert getattr(g, name) == pytest.approx(getattr(w, name), abs=1e-6), name
        assert (g.rows, g.cols) == (w.rows, w.cols) and g.pixel_mm == pytest.approx(w.pixel_mm, rel=1e-9)
        # 16-bit storage of the attenuation (see write_xray): within one stored step.
        assert np.abs(got.image[want.mask] - want.image[want.mask]).max() < 1e-3
    assert got_a.meta["acquisition_datetime"].startswith("20261201093015.25")
    assert got_b.meta["acquisition_datetime"].startswith("20261201093015.28")


def test_two_moments_are_refused(tmp_path):
    write_xray(_view(PLANE_A, 1), tmp_path / "a.dcm", uid_seed="a", plane="PLANE A", acquired_at=MOMENT)
    later = MOMENT + timedelta(seconds=2)
    write_xray(_view(PLANE_B, 2), tmp_path / "b.dcm", uid_seed="b", plane="PLANE B", acquired_at=later)
    with pytest.raises(ValueError, match=r"acquired 2\.000 s apart .*two different moments"):
        read_biplane([tmp_path / "a.dcm", tmp_path / "b.dcm"])
    assert PAIR_TOLERANCE_S < 2.0
    # Two files of one plane are no pair either.
    write_xray(_view(PLANE_A, 3), tmp_path / "a2.dcm", uid_seed="a2", plane="PLANE A", acquired_at=MOMENT)
    with pytest.raises(ValueError, match="both PLANE A"):
        read_biplane([tmp_path / "a.dcm", tmp_path / "a2.dcm"])
    # A single-plane file says so when read on its own.
    write_xray(_view(PLANE_A, 4), tmp_path / "mono.dcm", uid_seed="m")
    assert read_xray(tmp_path / "mono.dcm").meta["plane"] == ""
