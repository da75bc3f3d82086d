"""Clinical-looking images: each effect does what it says, on a small synthetic head."""

from __future__ import annotations

import warnings
from dataclasses import replace

import numpy as np
import pydicom
import pytest

from registration.core.geometry import CArm, rigid
from registration.core.volume import Volume
from registration.io import dicom
from registration.sim.clinical import (
    Blades,
    BurnedInText,
    ClinicalEffects,
    ClinicalImager,
    Display,
    Neck,
    Overlay,
    Scatter,
    Table,
    parse_realism,
)
from registration.sim.clinical.anatomy import bent_volume, neck_pivot_mm, patient_only
from registration.sim.clinical.display import display_pixels, lut

PIXELS = 96


@pytest.fixture(scope="module")
def head() -> Volume:
    """A 2 mm CT-like head: water ellipsoid in a 5 mm bone shell, a bony spine below it, and a
    couch plate (a 10 mm board) behind the patient over the whole length."""
    n = (70, 90, 90)  # k (z), j (y), i (x)
    spacing = 2.0
    kk, jj, ii = np.meshgrid(*(np.arange(s) for s in n), indexing="ij")
    x = (ii - 44.5) * spacing
    y = (jj - 44.5) * spacing
    z = (kk - 45.5) * spacing
    data = np.full(n, -1000.0, dtype=np.float32)
    r = np.sqrt((x / 70) ** 2 + (y / 68) ** 2 + (z / 60) ** 2)
    data[r < 1.0] = 1000.0
    data[r < 0.92] = 40.0
    neck = (np.hypot(x / 45, (y - 10) / 45) < 1.0) & (z < -20)
    data[neck] = 40.0
    spine = (np.hypot(x / 8, (y - 25) / 8) < 1.0) & (z < -35)
    data[spine] = 800.0
    data[(y > 76) & (y < 86) & (np.abs(x) < 80)] = 200.0  # the couch plate, 8 mm behind the head
    affine = np.diag([spacing, spacing, spacing, 1.0])
    affine[:3, 3] = [-44.5 * spacing, -44.5 * spacing, -45.5 * spacing]
    return Volume(data, affine, label="synthetic head")


def _geometry(primary: float = 0.0, secondary: float = 0.0, pixels: int = PIXELS) -> CArm:
    return CArm.for_format(27.0, pixels=pixels, primary_deg=primary, secondary_deg=secondary)


def _log_image(image) -> np.ndarray:  # noqa: ANN001
    """Attenuation from the project's LOG encoding (no display chain)."""
    return image.attenuation.astype(np.float64)


def test_blades_leave_no_signal_behind_straight_edges_at_the_asked_place(head: Volume) -> None:
    blades = Blades(shapes=("rectangular",), closed=(0.3, 0.2, 0.25, 0.35), rotation_deg=0.0, transmission=0.05)
    imager = ClinicalImager(head, (0, 0, 0), ClinicalEffects(blades=blades), catheter=False)
    g = _geometry()
    img = imager.image(g, kind="exposure", seed=3)
    att = _log_image(img)
    radius = g.field_diameter_mm / 2 / g.pixel_mm[1]
    c = (PIXELS - 1) / 2
    left, right = c - radius * 0.7, c + radius * 0.8
    top, bottom = c - radius * 0.75, c + radius * 0.65
    # the edges: the largest intensity jump of each half-profile through the center lies at the asked column/row
    intensity = np.exp(-att)
    row, col = intensity[int(c)], intensity[:, int(c)]
    assert abs(np.argmax(np.abs(np.diff(row[: int(c)]))) + 0.5 - left) <= 1.0  # within a pixel (penumbra 0.7 px)
    assert abs(int(c) + np.argmax(np.abs(np.diff(row[int(c) :]))) + 0.5 - right) <= 1.0
    assert abs(np.argmax(np.abs(np.diff(col[: int(c)]))) + 0.5 - top) <= 1.0
    assert abs(int(c) + np.argmax(np.abs(np.diff(col[int(c) :]))) + 0.5 - bottom) <= 1.0
    # straight: the edge's column is the same on every row across the open field (no anatomy bends it)
    rows = range(int(c) - 20, int(c) + 20)  # where the circular field's own edge lies farther out
    lo = int(left) - 6
    cols = [lo + np.argmax(np.abs(np.diff(intensity[r, lo : int(left) + 6]))) for r in rows]
    assert max(cols) - min(cols) <= 1 and abs(np.mean(cols) + 0.5 - left) <= 1.0
    # behind the blades: ln(1 / 0.05) = 3.0 more attenuation than without them; the open field unchanged
    clean = _log_image(
        ClinicalImager(head, (0, 0, 0), ClinicalEffects(), catheter=False).image(g, kind="exposure", seed=3)
    )
    rr, cc = np.mgrid[0:PIXELS, 0:PIXELS]
    far_behind = img.circle & (cc < left - 3)
    well_inside = img.field & (cc > left + 3) & (cc < right - 3) & (rr > top + 3) & (rr < bottom - 3)
    assert (att - clean)[far_behind].mean() == pytest.approx(np.log(1 / 0.05), abs=0.3)  # quantum noise at 5 % dose
    assert abs((att - clean)[well_inside].mean()) < 0.02  # noise only (12,000 photons)
    blade_zone = img.circle & ~img.field
    assert att[blade_zone].std() > 0.05  # noise, not a constant
    # the open field is exactly the rectangle
    expected = img.circle & (cc > left) & (cc < right) & (rr > top) & (rr < bottom)
    assert np.array_equal(img.field, expected)


def test_the_display_lut_is_monotone_and_the_display_chain_keeps_the_order() -> None:
    x = np.linspace(-2.0, 3.0, 20001)
    for d in (Display(), Display(s_curve=0.0, gamma=1.0), Display(s_curve=12.0, gamma=0.4), Display(gamma=2.5)):
        y = lut(x, d)
        assert np.all(np.diff(y) >= 0) and y[-1] > y[0]
        inside = (x >= 0) & (x <= 1)
        assert np.all(np.diff(y[inside]) > 0)  # strictly increasing over the window
    # without edge enhancement and JPEG, stored values are a monotone function of attenuation
    g = _geometry(pixels=32)
    att = np.linspace(0.0, 5.0, 32 * 32).reshape(32, 32).astype(np.float32)
    field = np.ones((32, 32), dtype=bool)
    for polarity, sign in (("bone_dark", -1), ("bone_bright", 1)):
        d = Display(bits=12, polarity=polarity, edge_amount=0.0, jpeg_quality=None)
        stored, _ = display_pixels(att, field, field, g, d)
        steps = np.diff(stored.ravel().astype(np.int64))
        assert np.all(sign * steps >= 0)  # quantised: equal neighbours allowed, never reversed


def test_scatter_adds_the_asked_fraction_of_the_primary(head: Volume) -> None:
    g = _geometry()
    clean = ClinicalImager(head, (0, 0, 0), ClinicalEffects(), catheter=False).image(g, kind="exposure", seed=5)
    for spr in (0.3, 0.5):
        img = ClinicalImager(head, (0, 0, 0), ClinicalEffects(scatter=Scatter(spr=spr)), catheter=False).image(
            g, kind="exposure", seed=5
        )
        rr, cc = np.mgrid[0:PIXELS, 0:PIXELS]
        c = (PIXELS - 1) / 2
        central = np.hypot(rr - c, cc - c) <= 0.5 * g.field_diameter_mm / 2 / g.pixel_mm[0]
        # intensity with scatter over the primary's: (P + S) / P, the I0 of the exposure control cancels
        ratio = np.exp(-_log_image(img))[central].mean() / np.exp(-_log_image(clean))[central].mean()
        assert ratio == pytest.approx(1 + spr, rel=0.05)  # quantum noise at 12,000 photons, the blur
        assert img.meta["spr_measured"] == pytest.approx(spr, rel=1e-6)


def test_the_table_is_in_the_image_and_does_not_move_with_the_patient(head: Volume) -> None:
    with_table = ClinicalImager(head, (0, 0, 0), ClinicalEffects(table=Table()), catheter=False)
    # the CT's couch plate is gone from the anatomy the images are formed from
    assert with_table.anatomy.data.max() <= 1000.0
    assert not np.any(patient_only(head)[0].data[:, 82:, :] > -500)  # the plate's rows (y 76..86 mm) are air
    g = _geometry(90.0, 0.0)  # lateral: the table top seen edge on
    rr, cc = np.mgrid[0:PIXELS, 0:PIXELS]
    targets = g.pixel_to_world(cc.ravel(), rr.ravel())
    moved = rigid(None, (0.0, -12.0, 8.0)) @ rigid(np.eye(3), None)
    static = []
    for m in (np.eye(4), moved):
        total = with_table.attenuator(m).line_integrals(g.source_mm, targets, m)
        patient = with_table.attenuator(m).patient.line_integrals(g.source_mm, targets, m)
        static.append(total - patient)
    assert np.abs(static[0]).max() > 0.5  # the table top edge on
    np.testing.assert_allclose(static[0], static[1], atol=1e-9)  # identical whatever the patient does


def test_the_neck_bend_moves_the_spine_less_than_the_skull(head: Volume) -> None:
    neck = Neck(flexion_deg=0.0, rotation_deg=0.0, follow=0.3, plane_below_iso_mm=30.0, anterior_cut_mm=20.0)
    motion = rigid(None, (10.0, 0.0, 0.0))
    bent = bent_volume(head, motion, (0, 0, 0), neck)
    z = head.index_to_world[2, 2] * np.arange(head.shape[0]) + head.index_to_world[2, 3]
    above = z > -30.0 + 3 * neck.blend_mm
    np.testing.assert_array_equal(bent.data[above], head.data[above])  # the skull: untouched

    def spine_x(vol: Volume) -> float:
        low = z < -60.0
        kk, jj, ii = np.nonzero((vol.data > 500) & low[:, None, None])
        return float(np.mean(ii) * vol.index_to_world[0, 0] + vol.index_to_world[0, 3])

    # moved by the motion, the spine ends up 0.3 x 10 mm away: in the volume it shifts by -7 mm
    assert spine_x(bent) - spine_x(head) == pytest.approx(-7.0, abs=0.3)  # trilinear resampling of 2 mm voxels
    pivot, _ = neck_pivot_mm(head, (0, 0, 0), neck)
    assert pivot[1] == pytest.approx(25.0, abs=4.0)  # the spine's center, behind the iso-center


def test_text_and_ruler_are_burned_in_at_full_white(head: Volume) -> None:
    effects = ClinicalEffects(display=Display(bits=10, jpeg_quality=None), text=BurnedInText())
    img = ClinicalImager(head, (0, 0, 0), effects, catheter=False).image(_geometry(pixels=192), seed=1)
    assert img.graphics.sum() > 200
    assert np.all(img.stored[img.graphics] == 1023)
    assert (img.graphics & img.circle).sum() > 50  # the angles and the ruler lie over the anatomy
    assert not np.any(img.field & img.graphics)
    assert img.stored[img.field].max() < 1023  # the soft limits of the look-up table keep anatomy below white


def test_dicom_of_a_clinical_image_reads_back(head: Volume, tmp_path) -> None:  # noqa: ANN001
    g = _geometry(20.0, 10.0, pixels=128)
    effects = ClinicalEffects(display=Display(bits=8), text=BurnedInText(), overlay=Overlay(), blades=Blades())
    img = ClinicalImager(head, (0, 0, 0), effects, catheter=False).image(g, seed=2)
    path = img.write_dicom(tmp_path / "xa.dcm")
    ds = pydicom.dcmread(path)
    assert ds.PixelIntensityRelationship == "DISP"
    assert ds.BitsStored == 8 and ds.file_meta.TransferSyntaxUID == pydicom.uid.JPEGBaseline8Bit
    assert ds.LossyImageCompression == "01" and ds.BurnedInAnnotation == "YES"
    overlay = ds.overlay_array(0x6000)
    assert np.array_equal(overlay.astype(bool), img.overlay)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        xray = dicom.read_xray(path)
    assert xray.geometry.primary_deg == pytest.approx(20.0) and xray.image.shape == (128, 128)
    # the decoded pixels are the JPEG of the stored ones: within the quantisation of quality 85
    decoded = ds.pixel_array.astype(np.int64)
    assert np.abs(decoded - img.stored.astype(np.int64))[img.field].mean() < 3.0
    # no relationship tag, 12 bits, bone bright, no sign, an overlay in the high bits
    d = Display(bits=12, relationship=None, sign_tag=False, polarity="bone_bright", jpeg_quality=None)
    effects = ClinicalEffects(display=d, overlay=Overlay(embedded=True))
    img = ClinicalImager(head, (0, 0, 0), effects, catheter=False).image(g, seed=2)
    ds = pydicom.dcmread(img.write_dicom(tmp_path / "xa12.dcm"))
    assert "PixelIntensityRelationship" not in ds and "PixelIntensityRelationshipSign" not in ds
    assert ds.BitsAllocated == 16 and ds.BitsStored == 12 and ds[0x60000102].value == 12
    raw = np.frombuffer(ds.PixelData, dtype=np.uint16).reshape(128, 128)
    assert np.array_equal((raw >> 12).astype(bool), img.overlay)


def test_effects_scale_with_strength_and_realism_parses() -> None:
    assert Blades().at_strength(0).closed == (0.0, 0.0, 0.0, 0.0)
    assert Scatter().at_strength(1.25).spr == pytest.approx(0.5)
    assert Neck().at_strength(0).follow == 1.0 and Neck().at_strength(0).flexion_deg == 0.0
    assert Display().at_strength(0).jpeg_quality is None
    assert ClinicalEffects.of(["overlay", "text"], 0.0).is_clean  # strength 0: no effect at all
    arms = parse_realism("clean,blades,text+display,clinical")
    assert [a for a, _ in arms] == ["clean", "blades", "display+text", "clinical"]
    assert arms[3][1] == tuple(ClinicalEffects.all().names)
    assert len(parse_realism("each")) == len(ClinicalEffects.all().names)
    with pytest.raises(ValueError, match="unknown effect 'shutters'"):
        parse_realism("shutters")
    with pytest.raises(ValueError, match=r"spr must lie in \[0, 5\]"):
        replace(Scatter(), spr=-1.0)
